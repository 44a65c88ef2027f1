"""``python -m fgslam.train``: see :mod:`fgslam.train.detector`."""

import sys

from fgslam.train.detector import main

sys.exit(main())

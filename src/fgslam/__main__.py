"""``python -m fgslam``."""

import sys

from fgslam.cli import main

sys.exit(main())

"""fgslam: iSAM2 smoother and the application (bags, runner, metrics, rerun, CLI)."""

from fgslam.errors import FgslamError

__version__ = "0.1.0"
__all__ = ["FgslamError", "__version__"]

"""Back-end constructors by name (``ekf``, ``isam2``, ``dr``) and the dead-reckoning reference."""

from fgslam.backends.dead_reckoning import DeadReckoning, DeadReckoningConfig
from fgslam.backends.registry import BACKEND_NAMES, available_backends, make_backend

__all__ = ["BACKEND_NAMES", "DeadReckoning", "DeadReckoningConfig", "available_backends", "make_backend"]

"""ekf: the EKF-SLAM baseline of the reference design (numpy/scipy only, no I/O)."""

from ekf.errors import EkfError

__all__ = ["EkfError"]

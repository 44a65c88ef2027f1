"""ekf: the EKF-SLAM baseline of the reference design (numpy/scipy only, no I/O)."""

from ekf.config import EkfConfig, FixGateConfig, MotionNoiseConfig
from ekf.errors import EkfError, EkfInputError
from ekf.slam import EkfSlam

__all__ = ["EkfConfig", "EkfError", "EkfInputError", "EkfSlam", "FixGateConfig", "MotionNoiseConfig"]

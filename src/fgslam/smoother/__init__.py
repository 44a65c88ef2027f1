"""GTSAM iSAM2 smoother back-end: keyframe poses, rock landmarks, late global fixes."""

from fgslam.smoother.config import (
    Factorization,
    FixConfig,
    KeyframeConfig,
    LandmarkConfig,
    OdometryNoiseConfig,
    SmootherConfig,
)
from fgslam.smoother.isam2_backend import Isam2Smoother

__all__ = [
    "Factorization",
    "FixConfig",
    "Isam2Smoother",
    "KeyframeConfig",
    "LandmarkConfig",
    "OdometryNoiseConfig",
    "SmootherConfig",
]

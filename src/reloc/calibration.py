"""Stereo calibration that the back-ends can estimate: the rock measurements' rotation error and
range scale (the mast camera's mounting and its baseline calibration are known only so well)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reloc.config import NonNegative, checked


@dataclass(frozen=True)
@checked()
class CalibrationConfig:
    """Stereo calibration states (off when every sigma is 0). The camera's mounting rotation and
    its range scale are known only to these sigmas (a rotation vector per axis, deg; a relative
    scale); a sigma of 0 keeps that term at its nominal value. When on, a back-end estimates the
    rotation error ``E`` and scale ``s`` of the rock measurements in base_link, ``z = s E q`` for
    the true point ``q`` (about the base origin: the camera's 0.9 m lever arm changes a 0.15 deg
    rotation's effect by ~2 mm)."""

    roll_pitch_sigma_deg: NonNegative = 0.0  # about base_link x and y
    # about base_link x alone, where it differs from the pitch's (None: roll_pitch_sigma_deg). A
    # mast camera tilted down turns a roll about its optical axis into a roll and a yaw of the
    # base; with the yaw held, a free roll let the landmarks turn the smoother's heading where
    # they are few (sparse-5km, docs/smoother.md)
    roll_sigma_deg: NonNegative | None = None
    yaw_sigma_deg: NonNegative = 0.0  # about base_link z
    scale_sigma: NonNegative = 0.0

    @property
    def enabled(self) -> bool:
        return bool(np.any(self.prior_sigmas() > 0))

    def prior_sigmas(self) -> np.ndarray:
        """(4,): rotation about x, y, z (rad) and scale."""
        roll = self.roll_pitch_sigma_deg if self.roll_sigma_deg is None else self.roll_sigma_deg
        return np.array([math.radians(roll), math.radians(self.roll_pitch_sigma_deg), math.radians(self.yaw_sigma_deg),
                         self.scale_sigma])


def calibration_report(rotvec_rad: np.ndarray, scale: float, rot_sigma_rad: np.ndarray, scale_sigma: float) -> dict:
    """JSON-ready estimate of a calibration, as both back-ends report it: rotation vector of ``E``
    (deg, base_link), range scale, and their sigmas."""
    return {"rotation_deg": np.degrees(np.asarray(rotvec_rad, dtype=float)).round(4).tolist(),
            "scale": round(float(scale), 6),
            "rotation_sigma_deg": np.degrees(np.asarray(rot_sigma_rad, dtype=float)).round(4).tolist(),
            "scale_sigma": round(float(scale_sigma), 6)}

"""Keyframe bookkeeping: times, the keyframe policy, the online (causal) history and the poses
frozen when a keyframe leaves the fixed-lag window."""

from __future__ import annotations

import bisect

import numpy as np

from fgslam.smoother.config import KeyframeConfig
from fgslam.smoother.odometry_factors import OdometryAccumulator


def keyframe_due(acc: OdometryAccumulator, cfg: KeyframeConfig) -> bool:
    """Whether the motion since the last keyframe calls for a new one (distance, yaw or time)."""
    return (
        acc.distance_m >= cfg.distance_m
        or acc.yaw_change_rad() >= cfg.yaw_rad
        or acc.t_now - acc.t_kf >= cfg.interval_s
    )


class KeyframeStore:
    """Keyframe ``i`` is the GTSAM variable ``X(i)`` at time ``t[i]``.

    ``online`` keeps, per keyframe, the estimate and covariance the smoother had right after adding
    it (the causal estimate, protocol convention); ``frozen`` the last smoothed estimate of a
    keyframe that was marginalized by the fixed-lag smoother.
    """

    def __init__(self) -> None:
        self.t: list[float] = []
        self.online_T: list[np.ndarray] = []
        self.online_cov: list[np.ndarray] = []
        self.frozen: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.t)

    def add(self, t: float) -> int:
        """Register a keyframe at ``t`` s; returns its index."""
        self.t.append(float(t))
        return len(self.t) - 1

    def record_online(self, T_world_base: np.ndarray, cov_world: np.ndarray) -> None:
        """Store the causal estimate (4, 4) / (6, 6) of the newest keyframe."""
        self.online_T.append(T_world_base.copy())
        self.online_cov.append(cov_world.copy())

    def before(self, t: float) -> int:
        """Index of the latest keyframe at or before ``t`` (-1 if none)."""
        return bisect.bisect_right(self.t, t) - 1

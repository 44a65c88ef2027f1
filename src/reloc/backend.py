"""The back-end protocol shared by the EKF and the iSAM2 smoother, and the types it exchanges.

The runner, the metrics and the viewer only talk to a back-end through :class:`Backend`, so the
EKF baseline and the smoother are interchangeable, and a new landmark type (craters) adds a
measurement and its update without touching the runner.

Pose covariance convention (both back-ends): a 6x6 matrix over the error
``[dp_world (3, m), dtheta_world (3, rad)]`` where the true pose is
``R_true = Exp(dtheta_world) @ R_est`` and ``p_true = p_est + dp_world``. So ``cov[:3, :3]`` is the
world-frame position covariance and ``cov[5, 5]`` is (for small roll/pitch) the yaw variance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from reloc.measurements import GlobalFix, RockObservations
from reloc.odometry import OdometryStep

# Uncertainty of a known start pose (the rover's landing site in the map), the same wherever a
# run starts from: a bag's first ground-truth message, --start, or a simulator run in memory.
KNOWN_START_SIGMA_POS_M = 0.01
KNOWN_START_SIGMA_ROT_RAD = 0.002


def known_start_cov() -> np.ndarray:
    """(6, 6) covariance over ``[dp_world, dtheta_world]`` of a known start pose."""
    return np.diag([KNOWN_START_SIGMA_POS_M**2] * 3 + [KNOWN_START_SIGMA_ROT_RAD**2] * 3)


@dataclass(frozen=True)
class PoseEstimate:
    """Pose of base_link in world at ``t``: ``T_world_base`` (4, 4) and ``cov`` (6, 6), see module doc."""

    t: float
    T_world_base: np.ndarray
    cov: np.ndarray

    @property
    def position_m(self) -> np.ndarray:
        return self.T_world_base[:3, 3]

    @property
    def yaw_rad(self) -> float:
        R = self.T_world_base[:3, :3]
        return float(np.arctan2(R[1, 0], R[0, 0]))


@dataclass(frozen=True)
class LandmarkMap:
    """The back-end's current local landmark map, in the (estimated) world frame.

    ``ids`` (N,) int, ``xyz_world_m`` (N, 3), ``cov_world_m2`` (N, 3, 3), ``size_m`` (N,) mean
    estimated diameter, ``n_obs`` (N,) number of associated observations.
    """

    ids: np.ndarray
    xyz_world_m: np.ndarray
    cov_world_m2: np.ndarray
    size_m: np.ndarray
    n_obs: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @staticmethod
    def empty() -> LandmarkMap:
        return LandmarkMap(
            ids=np.zeros(0, dtype=int),
            xyz_world_m=np.zeros((0, 3)),
            cov_world_m2=np.zeros((0, 3, 3)),
            size_m=np.zeros(0),
            n_obs=np.zeros(0, dtype=int),
        )


@dataclass(frozen=True)
class FixOutcome:
    """What a back-end did with a :class:`GlobalFix`.

    ``accepted`` False comes with a ``reason`` (e.g. "distance gate 4.2 m > 3.0 m",
    "older than history"); ``mahalanobis_d2`` is the fix innovation's squared Mahalanobis distance
    when it was computed.
    """

    fix: GlobalFix
    accepted: bool
    reason: str = ""
    mahalanobis_d2: float = float("nan")


@dataclass(frozen=True)
class LandmarkUpdateReport:
    """Outcome of one rock frame: how many detections were associated, initialised, rejected."""

    t: float
    n_detections: int
    n_associated: int
    n_new: int
    n_rejected: int


@dataclass(frozen=True)
class Trajectory:
    """A sequence of poses: ``t`` (K,), ``T_world_base`` (K, 4, 4), ``cov`` (K, 6, 6) or None."""

    t: np.ndarray
    T_world_base: np.ndarray
    cov: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def positions_m(self) -> np.ndarray:
        return self.T_world_base[:, :3, 3]


@dataclass(frozen=True)
class BackendStats:
    """Counters a back-end keeps for reports (free-form extras in ``extra``)."""

    n_predict: int = 0
    n_landmark_frames: int = 0
    n_fixes_accepted: int = 0
    n_fixes_rejected: int = 0
    n_landmarks: int = 0
    extra: dict = field(default_factory=dict)


@runtime_checkable
class Backend(Protocol):
    """A localization back-end. Inputs arrive in time order; a fix may arrive late
    (``fix.t_meas`` earlier than the last processed input) and must land at ``t_meas``.

    Constructors take the initial :class:`PoseEstimate` (the start pose in world is known) and a
    frozen config dataclass.
    """

    name: str

    def predict(self, step: OdometryStep) -> None:
        """Propagate with one odometry step (command velocity + IMU orientation increment)."""

    def update_landmarks(self, obs: RockObservations) -> LandmarkUpdateReport:
        """Associate, update and initialise landmarks from one stereo rock frame at ``obs.t``."""

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        """Apply a (possibly late) global planar fix at ``fix.t_meas``; gate it, never raise on a bad one."""

    def estimate(self) -> PoseEstimate:
        """Current (latest) pose with covariance."""

    def landmark_map(self) -> LandmarkMap:
        """Current local landmark map in the estimated world frame, for constellation matching."""

    def trajectory(self) -> Trajectory:
        """The back-end's best trajectory so far (filtered for the EKF, smoothed for iSAM2)."""

    def stats(self) -> BackendStats:
        """Counters for reports."""

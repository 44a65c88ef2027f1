"""The back-end protocol shared by the EKF and the iSAM2 smoother, and the types it exchanges.

The runner, the metrics and the viewer only talk to a back-end through :class:`Backend`, so the
EKF baseline and the smoother are interchangeable. Landmark observations of every kind enter
through one method, :meth:`Backend.observe`; a back-end dispatches them on the kind registry
(:mod:`reloc.kinds`) to that kind's update, so a new kind (craters) adds its modules and a
registration, never an edit of the runner or of a back-end's core.

Pose covariance convention (both back-ends): a 6x6 matrix over the error
``[dp_world (3, m), dtheta_world (3, rad)]`` where the true pose is
``R_true = Exp(dtheta_world) @ R_est`` and ``p_true = p_est + dp_world``. So ``cov[:3, :3]`` is the
world-frame position covariance and ``cov[5, 5]`` is (for small roll/pitch) the yaw variance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from reloc.config import config_to_dict
from reloc.kinds import LandmarkObservations
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep

# Uncertainty of a known start pose (the rover's landing site in the map), the same wherever a
# run starts from: a bag's first ground-truth message, --start, or a simulator run in memory.
KNOWN_START_SIGMA_POS_M = 0.01
KNOWN_START_SIGMA_ROT_RAD = 0.002

# Where the planar pose (x, y, yaw) sits in the pose covariance (see the module doc): world x, y,
# and the rotation about world z.
PLANAR_POSE_INDICES = (0, 1, 5)


def major_sigma(cov_xy) -> float:
    """The largest standard deviation of a (2, 2) planar covariance (its largest eigenvalue's root)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(cov_xy, dtype=float))[-1], 0.0)))


def offset_report(offset, sigma) -> dict:
    """A fix source's shared offset (x, y m, yaw rad; ``offset`` (3,)) and its sigmas (``sigma``
    (3,)) as both back-ends' stats report it (``extra["fix_offset"]``): metres and degrees."""
    f, s = (np.asarray(v, dtype=float) for v in (offset, sigma))
    return {"x_m": round(float(f[0]), 4), "y_m": round(float(f[1]), 4), "yaw_deg": round(math.degrees(f[2]), 4),
            "sigma_x_m": round(float(s[0]), 4), "sigma_y_m": round(float(s[1]), 4),
            "sigma_yaw_deg": round(math.degrees(s[2]), 4)}


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
    def planar_sigma_m(self) -> float:
        """The largest planar standard deviation (m) of the position (its x/y covariance's)."""
        return major_sigma(self.cov[:2, :2])

    @property
    def yaw_rad(self) -> float:
        R = self.T_world_base[:3, :3]
        return float(np.arctan2(R[1, 0], R[0, 0]))


@dataclass(frozen=True)
class LandmarkMap:
    """The back-end's current local map of one landmark kind, in the (estimated) world frame.

    ``ids`` (N,) int, ``xyz_world_m`` (N, 3), ``cov_world_m2`` (N, 3, 3), ``size_m`` (N,) mean
    estimated diameter, ``n_obs`` (N,) number of associated observations, ``kind`` the landmark
    kind's name (:mod:`reloc.kinds`). ``cov_world_m2`` is where the landmark is in the world, the
    back-end's drift included (the EKF's marginal; the smoother's map uncertainty plus the pose's
    when the landmark was last seen), not its position relative to the rover.
    ``catalog_row`` (N,) int: the catalog entry each landmark was anchored on
    (:class:`reloc.measurements.CatalogAnchor`), -1 for none (None: no landmark anchored).
    """

    ids: np.ndarray
    xyz_world_m: np.ndarray
    cov_world_m2: np.ndarray
    size_m: np.ndarray
    n_obs: np.ndarray
    kind: str
    catalog_row: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def anchored_rows(self) -> np.ndarray:
        """(N,) int: :attr:`catalog_row`, -1 everywhere when it is None."""
        if self.catalog_row is None:
            return np.full(len(self), -1, dtype=int)
        return np.asarray(self.catalog_row, dtype=int)

    @staticmethod
    def empty(kind: str) -> LandmarkMap:
        return LandmarkMap(
            ids=np.zeros(0, dtype=int),
            xyz_world_m=np.zeros((0, 3)),
            cov_world_m2=np.zeros((0, 3, 3)),
            size_m=np.zeros(0),
            n_obs=np.zeros(0, dtype=int),
            kind=kind,
        )


@dataclass(frozen=True)
class FixOutcome:
    """What a back-end did with a :class:`GlobalFix`.

    ``accepted`` False comes with a ``reason`` (e.g. "distance gate 4.2 m > 3.0 m",
    "older than history"); ``mahalanobis_d2`` is the fix innovation's squared Mahalanobis distance
    when it was computed. ``released``: the outcomes of earlier fixes that were held and went to
    the back-end with this one (:mod:`fgslam.fix_hold`), each replacing that fix's held outcome.
    ``t_applied``: when the back-end was given the fix (stream time), set where it waited (a held
    fix: the ``t_recv`` of the fix that released it); :attr:`applied_s` reads it.
    """

    fix: GlobalFix
    accepted: bool
    reason: str = ""
    mahalanobis_d2: float = float("nan")
    released: tuple[FixOutcome, ...] = ()
    t_applied: float | None = None

    @property
    def applied_s(self) -> float:
        """When the back-end was given the fix: ``t_applied``, or the fix's ``t_recv`` if it did not wait."""
        return self.fix.t_recv if self.t_applied is None else self.t_applied


@dataclass(frozen=True)
class LandmarkUpdateReport:
    """Outcome of one landmark frame: how many detections were associated, initialised, rejected."""

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
    frozen config dataclass, kept as ``config`` (the resolved config a run saves). Back-ends
    subclass this protocol, so they inherit the defaults of its optional capabilities
    (:meth:`expect_fix`).
    """

    name: str
    config: Any
    # CPU a pass of this back-end takes relative to the EKF's on the same stream (the demo's
    # rocky-1km: dead reckoning 0.3, iSAM2 fixed-lag 2); only orders a comparison's passes
    # (longest first, so that no long pass starts last and runs alone), never changes a result
    relative_cost: float = 1.0

    def predict(self, step: OdometryStep) -> None:
        """Propagate with one odometry step (command velocity + IMU orientation increment)."""

    def observe(self, obs: LandmarkObservations) -> LandmarkUpdateReport:
        """Associate, update and initialise landmarks from one frame of any registered landmark
        kind at ``obs.t``; an observation of no registered kind is an error (never a fix)."""

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        """Apply a (possibly late) global planar fix at ``fix.t_meas``; gate it, never raise on a bad one.
        A back-end may apply the fix's ``anchors`` (:class:`reloc.measurements.CatalogAnchor`) on
        its landmarks instead, when it holds every one of them, and then reports them in
        :attr:`LandmarkMap.catalog_row`."""

    def expect_fix(self, t_meas: float) -> None:
        """A fix for ``t_meas`` (at or after the newest input) may arrive later. A back-end that
        rolls back (the EKF) keeps a rollback point there; the default does nothing. Never
        changes results, only the cost of a late fix."""

    @classmethod
    def resolved_config(cls, config: Any) -> dict:
        """``config`` (this back-end's config dataclass) as the plain dict a run saves: every
        value, defaults included, so that it can be given back as overrides."""
        return config_to_dict(config)

    def estimate(self) -> PoseEstimate:
        """Current (latest) pose with covariance."""

    def landmark_map(self, kind: str) -> LandmarkMap:
        """Current local map of landmark kind ``kind`` in the estimated world frame (empty when
        none was observed), for constellation matching; an unregistered kind is an error."""

    def trajectory(self) -> Trajectory:
        """The back-end's best trajectory so far (filtered for the EKF, smoothed for iSAM2)."""

    def stats(self) -> BackendStats:
        """Counters for reports."""

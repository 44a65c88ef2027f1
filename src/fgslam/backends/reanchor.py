"""Lost and found: a back-end that starts lost re-anchors on its first global fix.

With the start pose unknown (or tens of metres and degrees off, its covariance saying so), no
back-end can fuse the first fix as a small correction: the EKF's linearisation and the
smoother's robust kernel both assume the fix is near the estimate. The relocalizer searches the
whole catalog while the estimate is lost (``RelocalizerConfig.lost_sigma_m``); the first fix it
finds re-anchors the back-end: the planar rigid motion ``D`` that takes the estimate at the fix's
``t_meas`` onto the fix is applied to the current estimate, and the back-end starts anew there,
its covariance the fix's plus the odometry's growth since ``t_meas`` (the wrapped back-end's own,
not the anchor's: the fix replaces the start's uncertainty). Its past (the trajectory
before the fix) is moved by the same ``D``. Afterwards the fixes take the prior-guided path and
reach the back-end as usual.

While lost, the wrapped back-end does not carry the start's uncertainty itself: it starts at the
given pose with a known start's covariance (roll and pitch as given: the IMU's) and estimates the
path relative to it, and the start's planar uncertainty (x, y, z, yaw: the *anchor*) is added to
what it reports, to first order: a pose at ``p`` gets ``J S J^T``, ``J`` taking a start shift
``dp`` and turn ``dyaw`` about the start position ``p0`` to ``dp + dyaw z x (p - p0)`` and
``dyaw``. The path relative to the start is independent of where the start is, so the sum is the
covariance a back-end with the wide start prior would report, without putting tens of metres of
prior beside the millimetres of odometry into one linear system (iSAM2's Cholesky declared such a
system indeterminate at its first keyframe and went on without its landmark factors, so that its
map never matched the catalog).

:class:`Reanchoring` wraps any back-end built by a factory; it is used when the start pose's
position sigma exceeds ``lost_sigma_m`` (:func:`fgslam.backends.registry.make_backend`).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable

import numpy as np

from reloc.backend import (
    PLANAR_POSE_INDICES,
    Backend,
    BackendStats,
    FixOutcome,
    PoseEstimate,
    Trajectory,
    known_start_cov,
)
from reloc.geometry import wrap_angle
from reloc.measurements import GlobalFix

LOST_SIGMA_M = 5.0  # a pose whose largest planar sigma exceeds this is lost
HISTORY_S = 120.0  # estimates kept while lost, to find the one at a late fix's t_meas
_ANCHOR_AXES = [0, 1, 2, 5]  # the start's uncertainty the anchor takes: x, y, z, yaw of [dp_world, dtheta_world]


def split_start(initial: PoseEstimate) -> tuple[PoseEstimate, np.ndarray]:
    """A lost start -> (the start the wrapped back-end is given: the same pose with a known
    start's covariance, roll and pitch as given; the anchor's (4, 4) covariance over x, y, z, yaw
    (m, rad), what the given covariance holds beyond the known start's there)."""
    cov = np.asarray(initial.cov, dtype=float)
    inner = known_start_cov()
    inner[3:5, 3:5] = cov[3:5, 3:5]  # roll and pitch: the IMU's, not the anchor's
    sel = np.ix_(_ANCHOR_AXES, _ANCHOR_AXES)
    anchor = 0.5 * (cov[sel] + cov[sel].T) - inner[sel]
    w, V = np.linalg.eigh(anchor)
    anchor = (V * np.clip(w, 0.0, None)) @ V.T
    return PoseEstimate(initial.t, np.asarray(initial.T_world_base, dtype=float).copy(), inner), anchor


def anchor_cov(anchor: np.ndarray, p0: np.ndarray, positions_m: np.ndarray) -> np.ndarray:
    """(K, 6, 6) covariance over ``[dp_world, dtheta_world]`` that the anchor's uncertainty
    (4, 4 over x, y, z, yaw of the start at ``p0``) adds to poses at ``positions_m`` (K, 3)."""
    d = np.asarray(positions_m, dtype=float).reshape(-1, 3) - np.asarray(p0, dtype=float)[:3]
    J = np.zeros((len(d), 6, 4))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = J[:, 5, 3] = 1.0
    J[:, 0, 3], J[:, 1, 3] = -d[:, 1], d[:, 0]  # a turn of the start about p0 swings the pose
    return np.einsum("kij,jl,kml->kim", J, anchor, J)


def is_lost(est: PoseEstimate, lost_sigma_m: float = LOST_SIGMA_M) -> bool:
    """Whether the largest planar position sigma of ``est`` exceeds ``lost_sigma_m``."""
    return est.planar_sigma_m > lost_sigma_m


def planar_motion(xyyaw_from: np.ndarray, xyyaw_to: np.ndarray) -> np.ndarray:
    """(4, 4) rotation about z and translation taking planar pose ``xyyaw_from`` onto ``xyyaw_to``."""
    a = float(wrap_angle(xyyaw_to[2] - xyyaw_from[2]))
    c, s = np.cos(a), np.sin(a)
    D = np.eye(4)
    D[:2, :2] = [[c, -s], [s, c]]
    D[:2, 3] = np.asarray(xyyaw_to[:2]) - D[:2, :2] @ np.asarray(xyyaw_from[:2])
    return D


class Reanchoring(Backend):
    """``make(initial)`` -> back-end, started at ``initial`` and re-anchored on the first fix
    while lost (see module doc). Everything else is the wrapped back-end's."""

    def __init__(self, make: Callable[[PoseEstimate], Backend], initial: PoseEstimate,
                 lost_sigma_m: float = LOST_SIGMA_M) -> None:
        self._make = make
        self.lost_sigma_m = lost_sigma_m
        self._anchor: np.ndarray | None = None  # the start's uncertainty while lost (see module doc)
        self._p0 = np.asarray(initial.T_world_base, dtype=float)[:3, 3].copy()
        if is_lost(initial, lost_sigma_m):
            initial, self._anchor = split_start(initial)
        self.inner = make(initial)
        self.name = self.inner.name
        self.config = self.inner.config
        self._history: deque[PoseEstimate] = deque()
        self._past: list[Trajectory] = []  # the path before the latest re-anchoring (earlier ones in it), moved
        self.reanchors: list[dict] = []

    @property
    def lost(self) -> bool:
        return is_lost(self.estimate(), self.lost_sigma_m)

    def _anchored(self, est: PoseEstimate) -> PoseEstimate:
        """``est`` of the wrapped back-end with the anchor's uncertainty added (none after a re-anchoring)."""
        if self._anchor is None:
            return est
        extra = anchor_cov(self._anchor, self._p0, est.position_m[None, :])[0]
        return PoseEstimate(est.t, est.T_world_base, np.asarray(est.cov, dtype=float) + extra)

    def predict(self, step) -> None:
        self.inner.predict(step)
        if not self.reanchors:  # only while lost: the estimates a late first fix is placed on
            est = self.inner.estimate()  # the wrapped back-end's own: relative to the start, no anchor
            self._history.append(est)
            while self._history and self._history[0].t < est.t - HISTORY_S:
                self._history.popleft()

    def observe(self, obs):
        return self.inner.observe(obs)

    def expect_fix(self, t_meas: float) -> None:
        self.inner.expect_fix(t_meas)

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        if not self.lost:
            return self.inner.apply_fix(fix)
        then = self._at(fix.t_meas)
        if then is None:
            return FixOutcome(fix, False, "lost, and t_meas is older than the pose history kept while lost")
        now = self.inner.estimate()
        D = planar_motion(np.array([then.position_m[0], then.position_m[1], then.yaw_rad]), fix.xyyaw)
        T = D @ now.T_world_base
        cov = known_start_cov()
        # the odometry's growth since t_meas, from the wrapped back-end's own estimates: the anchor's
        # lever arm (the start's yaw swinging a pose far from the start) is what the fix replaces
        growth = np.clip(np.diag(now.cov) - np.diag(then.cov), 0.0, None)
        i = list(PLANAR_POSE_INDICES)
        cov[np.ix_(i, i)] = np.asarray(fix.cov_xyyaw) + np.diag(growth[i])
        past = self.trajectory()
        self._past = [Trajectory(past.t, np.einsum("ij,njk->nik", D, past.T_world_base), past.cov)]
        self.inner = self._make(PoseEstimate(now.t, T, cov))
        self._anchor = None
        self._history.clear()
        shift = float(np.hypot(*D[:2, 3]))
        self.reanchors.append({"t_meas": fix.t_meas, "t": now.t, "shift_m": shift,
                               "rotation_deg": float(np.degrees(np.arctan2(D[1, 0], D[0, 0])))})
        return FixOutcome(fix, True, f"re-anchored: {shift:.1f} m, "
                                     f"{self.reanchors[-1]['rotation_deg']:.1f} deg")

    def _at(self, t: float) -> PoseEstimate | None:
        if not self._history or t < self._history[0].t - 1e-6:
            return None
        ts = np.array([e.t for e in self._history])
        return self._history[int(np.clip(np.searchsorted(ts, t), 0, len(ts) - 1))]

    def estimate(self) -> PoseEstimate:
        return self._anchored(self.inner.estimate())

    def landmark_map(self, kind: str):
        """The wrapped back-end's map, its world covariances with the anchor's uncertainty added
        while lost (a landmark is where the world frame is: :class:`reloc.backend.LandmarkMap`), so
        that a landmark's gate holds the start's uncertainty, as the estimate's does."""
        lmap = self.inner.landmark_map(kind)
        if self._anchor is None or len(lmap) == 0:
            return lmap
        extra = anchor_cov(self._anchor, self._p0, lmap.xyz_world_m)[:, :3, :3]
        return dataclasses.replace(lmap, cov_world_m2=np.asarray(lmap.cov_world_m2, dtype=float) + extra)

    def trajectory(self) -> Trajectory:
        """The path before the latest re-anchoring (moved by each), then the current back-end's
        (with the anchor's uncertainty while lost)."""
        cur = self.inner.trajectory()
        if self._anchor is not None and cur.cov is not None and len(cur):
            cur = Trajectory(cur.t, cur.T_world_base, cur.cov + anchor_cov(self._anchor, self._p0, cur.T_world_base[:, :3, 3]))
        if not self._past:
            return cur
        nxt = self.reanchors[-1]["t"]  # the path before the latest re-anchoring (every earlier one in it)
        p = self._past[0]
        parts = [Trajectory(p.t[p.t < nxt], p.T_world_base[p.t < nxt], None if p.cov is None else p.cov[p.t < nxt]), cur]
        covs = [p.cov for p in parts]
        return Trajectory(np.concatenate([p.t for p in parts]), np.concatenate([p.T_world_base for p in parts]),
                          None if any(c is None for c in covs) else np.concatenate(covs))

    def stats(self) -> BackendStats:
        s = self.inner.stats()
        n_re = len(self.reanchors)
        return BackendStats(s.n_predict, s.n_landmark_frames, s.n_fixes_accepted + n_re, s.n_fixes_rejected,
                            s.n_landmarks, {**s.extra, "reanchors": list(self.reanchors)})

    def __getattr__(self, name: str):  # the wrapped back-end's own extras (state size, calibration, ...)
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)

"""Dead reckoning as a :class:`reloc.backend.Backend`: the odometry-only curve of the plots.

Position integrates the commanded speed along the IMU attitude; the covariance grows with a
simple speed-proportional model (same convention as reloc.backend). Landmark frames of every
registered kind are turned into one world-frame map per kind by nearest-neighbour association of
their points (:class:`reloc.kinds.LandmarkObservations`), so a relocalizer can be exercised
without a SLAM back-end. Fixes are ignored unless ``use_fixes``; when used, the planar correction
that moves the pose at ``t_meas`` onto the fix is applied to the current pose and the maps.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from fgslam.errors import FgslamError
from reloc.backend import (
    PLANAR_POSE_INDICES,
    Backend,
    BackendStats,
    FixOutcome,
    LandmarkMap,
    LandmarkUpdateReport,
    PoseEstimate,
    Trajectory,
)
from reloc.config import NonNegative, Positive, checked
from reloc.geometry import skew
from reloc.kinds import UnknownKindError, kind_named, kind_of
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep


@dataclass(frozen=True)
@checked()
class DeadReckoningConfig:
    """Noise model and map-building parameters (defaults in code)."""

    sigma_speed_frac: NonNegative = 0.03  # 1-sigma relative speed error (slip), per unit distance
    sigma_lateral_frac: NonNegative = 0.01  # 1-sigma lateral drift per metre travelled
    sigma_yaw_rate_radps: NonNegative = 0.002  # 1-sigma random-walk density of heading, rad/sqrt(s)
    sigma_z_frac: NonNegative = 0.02
    association_gate_m: Positive = 0.6  # nearest landmark within this distance is the same one
    use_fixes: bool = False
    build_map: bool = True  # False: ignore landmark frames (the odometry-only curve needs no map)


FUTURE_TOLERANCE_S = 0.1  # a fix up to this far ahead of the odometry is applied now


class DeadReckoningError(FgslamError):
    """The dead-reckoning back-end was given an observation of no registered landmark kind."""


class _PointMap:
    """One kind's world-frame map: positions (N, 3), covariances (N, 3, 3) of the sightings
    fused, the rover's position covariance when each was last seen (N, 3, 3), sizes, counts;
    arrays grown by doubling, and a grid of ``cell_m`` cells (the association gate) over x, y,
    so that the landmarks within the gate of a point are those of its 3 x 3 cells: finding the
    nearest costs what a neighbourhood holds, not what the whole map does (the scan of every
    landmark made a 250 m traverse's map 224 s, growing with the square of the distance)."""

    def __init__(self, cell_m: float) -> None:
        self.cell_m = float(cell_m)
        self.count = 0
        self._xyz = np.zeros((16, 3))
        self._cov = np.zeros((16, 3, 3))
        self._pose_cov = np.zeros((16, 3, 3))
        self._size = np.zeros(16)
        self._n = np.zeros(16, dtype=int)
        self._cells: dict[tuple[int, int], list[int]] = {}
        self._cell_of: list[tuple[int, int]] = []

    xyz = property(lambda self: self._xyz[:self.count])
    cov = property(lambda self: self._cov[:self.count])
    pose_cov = property(lambda self: self._pose_cov[:self.count])
    size = property(lambda self: self._size[:self.count])
    n = property(lambda self: self._n[:self.count])

    def _cell(self, xy) -> tuple[int, int]:
        return (math.floor(xy[0] / self.cell_m), math.floor(xy[1] / self.cell_m))

    def nearest(self, xy: np.ndarray) -> tuple[int, float]:
        """(index, planar distance) of the nearest landmark if one is within ``cell_m`` of ``xy``
        (the lowest index among equally near ones), else (-1, inf)."""
        cx, cy = self._cell(xy)
        near = sorted(i for dx in (-1, 0, 1) for dy in (-1, 0, 1) for i in self._cells.get((cx + dx, cy + dy), ()))
        if not near:
            return -1, math.inf
        d = np.linalg.norm(self._xyz[near, :2] - xy[:2], axis=1)
        j = int(np.argmin(d))
        return (near[j], float(d[j])) if d[j] < self.cell_m else (-1, math.inf)

    def add(self, xyz, cov, pose_cov, size: float) -> None:
        if self.count == len(self._xyz):  # full: every array doubles
            for name in ("_xyz", "_cov", "_pose_cov", "_size", "_n"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.zeros_like(a)]))
        i = self.count
        self._xyz[i], self._cov[i], self._pose_cov[i], self._size[i], self._n[i] = xyz, cov, pose_cov, size, 1
        self.count += 1
        cell = self._cell(self._xyz[i])
        self._cells.setdefault(cell, []).append(i)
        self._cell_of.append(cell)

    def moved(self, i: int) -> None:
        """Landmark ``i``'s position changed: its cell follows."""
        cell = self._cell(self._xyz[i])
        if cell != self._cell_of[i]:
            self._cells[self._cell_of[i]].remove(i)
            self._cells.setdefault(cell, []).append(i)
            self._cell_of[i] = cell

    def transform(self, R: np.ndarray, t: np.ndarray) -> None:
        """Move every landmark by ``x -> R x + t`` (a fix's correction) and re-grid them."""
        self._xyz[:self.count] = self.xyz @ R.T + t
        self._cells.clear()
        self._cell_of = [self._cell(p) for p in self._xyz[:self.count]]
        for i, cell in enumerate(self._cell_of):
            self._cells.setdefault(cell, []).append(i)


class DeadReckoning(Backend):
    """Odometry-only back-end (see module doc); ``name`` is "dr"."""

    name = "dr"
    relative_cost = 0.3  # the demo: 24 s against the EKF's 77 s (3 s against 66 s with the front-end shared)

    def __init__(self, initial: PoseEstimate, config: DeadReckoningConfig | None = None) -> None:
        self.config = config or DeadReckoningConfig()
        self._T = np.array(initial.T_world_base, dtype=float)
        self._P = np.array(initial.cov, dtype=float)
        self._t = float(initial.t)
        self._hist_t: list[float] = [self._t]
        self._hist_T: list[np.ndarray] = [self._T.copy()]
        self._hist_P: list[np.ndarray] = [self._P.copy()]
        self._maps: dict[str, _PointMap] = {}
        self._stats = {"n_predict": 0, "n_landmark_frames": 0, "n_fixes_accepted": 0, "n_fixes_rejected": 0}

    def predict(self, step: OdometryStep) -> None:
        """Integrate one odometry step: attitude by the IMU increment, position by v*dt along x. A
        step ending at or before the current time (e.g. before the start pose) is ignored."""
        if step.t1 <= self._t:
            return
        c = self.config
        R0 = self._T[:3, :3]
        R1 = R0 @ step.dR_base
        ds = step.v_mps * step.dt
        dp = 0.5 * (R0 + R1) @ np.array([ds, 0.0, 0.0])
        F = np.eye(6)
        F[:3, 3:] = -skew(dp)
        Q_body = np.diag([(c.sigma_speed_frac * ds) ** 2, (c.sigma_lateral_frac * abs(ds)) ** 2, (c.sigma_z_frac * abs(ds)) ** 2])
        Q = np.zeros((6, 6))
        Q[:3, :3] = R1 @ Q_body @ R1.T
        Q[5, 5] = c.sigma_yaw_rate_radps**2 * step.dt
        Q[3, 3] = Q[4, 4] = 1e-8 * step.dt
        self._P = F @ self._P @ F.T + Q
        self._T[:3, :3] = R1
        self._T[:3, 3] += dp
        self._t = step.t1
        self._hist_t.append(self._t)
        self._hist_T.append(self._T.copy())
        self._hist_P.append(self._P.copy())
        self._stats["n_predict"] += 1

    def observe(self, obs) -> LandmarkUpdateReport:
        """Add the frame's landmarks to their kind's world map at the dead-reckoned pose (no pose
        correction)."""
        try:
            kind = kind_of(obs)
        except UnknownKindError as exc:
            raise DeadReckoningError(f"dead reckoning cannot observe {type(obs).__name__}: {exc}") from None
        self._stats["n_landmark_frames"] += 1
        n = len(obs)
        if n == 0 or not self.config.build_map:
            return LandmarkUpdateReport(obs.t, 0, 0, 0, 0)
        lm = self._maps.setdefault(kind.name, _PointMap(self.config.association_gate_m))
        R, p = self._T[:3, :3], self._T[:3, 3]
        xyz_w = obs.xyz_base_m @ R.T + p
        cov_w = R @ obs.cov_base_m2 @ R.T
        n_assoc = n_new = 0
        for k in range(n):
            j, _ = lm.nearest(xyz_w[k])
            if j >= 0:  # the nearest landmark within the gate is the same one
                # information-weighted fusion of the new sighting into landmark j
                Pj_inv = np.linalg.inv(lm.cov[j])
                Pk_inv = np.linalg.inv(cov_w[k])
                P_new = np.linalg.inv(Pj_inv + Pk_inv)
                lm.xyz[j] = P_new @ (Pj_inv @ lm.xyz[j] + Pk_inv @ xyz_w[k])
                lm.cov[j] = 0.5 * (P_new + P_new.T)
                lm.pose_cov[j] = self._P[:3, :3]
                m = lm.n[j]
                lm.size[j] = (m * lm.size[j] + obs.size_m[k]) / (m + 1)
                lm.n[j] += 1
                lm.moved(j)
                n_assoc += 1
                continue
            lm.add(xyz_w[k], cov_w[k], self._P[:3, :3], obs.size_m[k])
            n_new += 1
        return LandmarkUpdateReport(obs.t, n, n_assoc, n_new, 0)

    def _pose_at(self, t: float) -> tuple[int, np.ndarray]:
        i = bisect.bisect_right(self._hist_t, t) - 1
        return max(i, 0), self._hist_T[max(i, 0)]

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        """Ignored unless ``use_fixes``; then shift the current pose and map by the planar correction
        (and the height's, for a fix with one)."""
        if not self.config.use_fixes:
            self._stats["n_fixes_rejected"] += 1
            return FixOutcome(fix, accepted=False, reason="dead reckoning ignores fixes")
        if fix.t_meas < self._hist_t[0]:
            self._stats["n_fixes_rejected"] += 1
            return FixOutcome(fix, accepted=False, reason="older than history")
        if fix.t_meas > self._t + FUTURE_TOLERANCE_S:
            self._stats["n_fixes_rejected"] += 1
            return FixOutcome(fix, accepted=False,
                              reason=f"ahead of the odometry (t_meas {fix.t_meas:.3f} s > {self._t:.3f} s)")
        _, T_old = self._pose_at(fix.t_meas)
        yaw_old = float(np.arctan2(T_old[1, 0], T_old[0, 0]))
        dyaw = fix.yaw_rad - yaw_old
        c, s = np.cos(dyaw), np.sin(dyaw)
        R2 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        dz = 0.0 if fix.height is None else fix.height.z_m - T_old[2, 3]  # a height moves z as well
        t2 = np.array([fix.x_m, fix.y_m, dz]) - R2 @ np.array([T_old[0, 3], T_old[1, 3], 0.0])
        self._T[:3, :3] = R2 @ self._T[:3, :3]
        self._T[:3, 3] = R2 @ self._T[:3, 3] + t2
        for lm in self._maps.values():
            lm.transform(R2, t2)
        idx = list(PLANAR_POSE_INDICES) + ([] if fix.height is None else [2])  # the fix's (x, y, yaw[, z]) in [p, theta]
        C = fix.cov
        for a in range(len(idx)):
            for b in range(len(idx)):
                self._P[idx[a], idx[b]] = C[a, b]
        for a in idx:
            for b in {2, 3, 4} - set(idx):
                self._P[a, b] = self._P[b, a] = 0.0
        self._stats["n_fixes_accepted"] += 1
        return FixOutcome(fix, accepted=True)

    def estimate(self) -> PoseEstimate:
        """Latest dead-reckoned pose with its covariance."""
        return PoseEstimate(self._t, self._T.copy(), self._P.copy())

    def landmark_map(self, kind: str) -> LandmarkMap:
        """The map of ``kind`` built at the dead-reckoned poses, in the world frame; each
        landmark's covariance is its sightings' plus the rover's position covariance when it was
        last seen (where it is in the world, as :class:`reloc.backend.LandmarkMap` says)."""
        try:
            kind_named(kind)
        except UnknownKindError as exc:
            raise DeadReckoningError(str(exc)) from None
        lm = self._maps.get(kind)
        if lm is None:
            return LandmarkMap.empty(kind)
        return LandmarkMap(
            ids=np.arange(len(lm.xyz)),
            xyz_world_m=lm.xyz.copy(),
            cov_world_m2=lm.cov + lm.pose_cov,
            size_m=lm.size.copy(),
            n_obs=lm.n.copy(),
            kind=kind,
        )

    def trajectory(self) -> Trajectory:
        """Every integrated pose (t (K,), T (K,4,4), cov (K,6,6))."""
        return Trajectory(np.array(self._hist_t), np.array(self._hist_T), np.array(self._hist_P))

    def stats(self) -> BackendStats:
        return BackendStats(n_landmarks=sum(len(lm.xyz) for lm in self._maps.values()), **self._stats)

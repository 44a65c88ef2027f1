"""The rock kind's smoother layer: rock frames -> bearing-range factors on keyframes, rocks as
Point3 variables (key symbol from the kind, ``l``), fixed-lag retirement, and the rock map.

A frame is associated with the rock map through the shared front-end
(:class:`fgslam.smoother.landmarks.LandmarkStore`), its detections moved onto the current
keyframe through the odometry since it (their covariance grows by that odometry's); each graph
rock gets at most one factor per keyframe. A candidate enters the graph with all its pending
factors once it is constrained from enough keyframes. The settings are
``SmootherConfig.landmarks``; see :mod:`fgslam.smoother.kinds` for the seam.
"""

from __future__ import annotations

import gtsam
import numpy as np

from fgslam.smoother.factors import calibration_cov, make_calibrated_point_factor, make_point_factor
from fgslam.smoother.kinds import POINT3, KeyframeFrame
from fgslam.smoother.landmarks import ACTIVE, LandmarkStore
from reloc.backend import LandmarkMap, LandmarkUpdateReport
from reloc.geometry import skew
from reloc.kinds import LandmarkKind
from reloc.measurements import RockObservations


def considered_calibration_cov(config) -> np.ndarray:
    """(4, 4): the calibration prior a layer considers in its measurements' covariance
    (``SmootherConfig.calibration_consider_scale`` times the prior's)."""
    return config.calibration_consider_scale * np.diag(config.calibration.prior_sigmas() ** 2)


class RockLandmarks:
    """Rocks in the smoother (see module doc)."""

    variable = POINT3

    def __init__(self, config, kind: LandmarkKind, calib_key: int | None) -> None:
        self.cfg = config.landmarks
        self.kind = kind.name
        self.symbol = kind.symbol
        self.calib_key = calib_key
        cal = config.calibration
        # "consider": the calibration prior's effect on each measurement joins its covariance
        self._consider_cov = (considered_calibration_cov(config)
                              if cal.enabled and calib_key is None and config.calibration_mode == "consider" else None)
        self.store = LandmarkStore(self.cfg)
        self.n_frames = self.n_frames_skipped = 0
        self._last_frame_t = -np.inf
        self._buf_ids: set[int] = set()  # rocks with values or factors in the coming update
        self._seen_on_kf: set[int] = set()  # graph rocks that already have a factor on this keyframe
        self.anchored: dict[int, int] = {}  # landmark id -> the catalog entry put on it (anchor_key)

    def key(self, lid: int) -> int:
        return gtsam.symbol(self.symbol, lid)

    def anchor_key(self, lid: int, solver) -> int | None:
        """The variable of landmark ``lid`` when it is one of the solver's (in the graph, not yet
        marginalized), for a catalog anchor (:class:`reloc.measurements.CatalogAnchor`); None otherwise."""
        rec = self.store.records.get(int(lid))
        if rec is None or rec.status != ACTIVE or not solver.alive(self.key(rec.lid)):
            return None
        return self.key(rec.lid)

    def observe(self, obs: RockObservations, frame: KeyframeFrame) -> LandmarkUpdateReport:
        """Associate one rock frame; buffer factors on the current keyframe for the next update."""
        n = len(obs)
        if n == 0 or obs.t - self._last_frame_t < self.cfg.min_frame_interval_s:
            self.n_frames_skipped += int(n > 0)
            return LandmarkUpdateReport(obs.t, n, 0, 0, 0)
        self.n_frames += 1
        self._last_frame_t = obs.t
        kf = frame.kf
        T_rel, C_rel = frame.T_kf_now, frame.cov_kf_now
        R_rel = T_rel[:3, :3]
        z = np.asarray(obs.xyz_base_m)
        Rz = np.asarray(obs.cov_base_m2) * self.cfg.rock_cov_scale
        if self._consider_cov is not None:
            Rz = Rz + calibration_cov(z, self._consider_cov)
        # the observation moved onto the keyframe through the odometry since it
        z_kf = z @ R_rel.T + T_rel[:3, 3]
        J = np.zeros((n, 3, 6))
        J[:, :, :3] = -R_rel @ skew(z)
        J[:, :, 3:] = R_rel
        R_kf = R_rel @ Rz @ R_rel.T + J @ C_rel @ np.swapaxes(J, 1, 2)
        fa = self.store.associate_frame(
            obs.t, kf, frame.T_world_kf @ T_rel, C_rel, z, Rz, np.asarray(obs.size_m), z_kf, R_kf, frame.cov_growth
        )
        for lid, zk, Rk in fa.observed:
            if lid in self._seen_on_kf:
                continue
            self._seen_on_kf.add(lid)
            frame.graph.add(self._point_factor(kf, lid, zk, Rk))
            self._buf_ids.add(lid)
        for rec in fa.to_insert:
            rec.status = ACTIVE
            frame.values.insert(self.key(rec.lid), np.asarray(rec.xyz_world_m, dtype=float))
            self._buf_ids.add(rec.lid)
            self._seen_on_kf.add(rec.lid)
            for kf_i, zk, Rk in rec.pending:
                frame.graph.add(self._point_factor(kf_i, rec.lid, zk, Rk))
            rec.pending = []
        return LandmarkUpdateReport(obs.t, n, fa.n_associated, fa.n_new, fa.n_rejected)

    def _point_factor(self, kf: int, lid: int, z_kf: np.ndarray, R_kf: np.ndarray):
        k = self.cfg.huber_k
        if self.calib_key is not None:
            return make_calibrated_point_factor(gtsam.symbol("x", kf), self.key(lid), self.calib_key, z_kf, R_kf, k)
        return make_point_factor(gtsam.symbol("x", kf), self.key(lid), z_kf, R_kf, k)

    def buffered_stamps(self, t: float) -> dict[int, float]:
        return {self.key(lid): t for lid in self._buf_ids}

    def on_keyframe(self) -> None:
        self._buf_ids = set()
        self._seen_on_kf = set()

    def drop(self, index: int) -> None:
        self.store.drop(index)

    def marginalize(self, index: int, solver) -> None:
        rec = self.store.records.get(index)
        if rec is not None:
            rec.xyz_world_m = solver.estimate(self.key(index))
            self.store.retire(rec.lid)

    def prune(self, t: float, oldest_kf: int) -> None:
        self.store.prune_candidates(t, oldest_kf)

    def refresh(self, T_world_kf: np.ndarray, solver) -> None:
        """Cache the view around the newest keyframe; pull the solver's positions of the rocks in it."""
        self.store.set_view_cache(T_world_kf[:3, 3])
        for rec in self.store.in_view(T_world_kf[:3, :3], T_world_kf[:3, 3]):
            if rec.status == ACTIVE and solver.alive(self.key(rec.lid)):
                rec.xyz_world_m = solver.estimate(self.key(rec.lid))

    @property
    def n_landmarks(self) -> int:
        return len(self.store.mapped())

    def landmark_map(self, pose_cov_at=None) -> LandmarkMap:
        """Rocks in the graph (and those retired from the fixed-lag window), world frame. A
        record's covariance is its uncertainty relative to the map around it (what association
        needs); ``pose_cov_at(t)`` (K,) -> (K, 3, 3), the rover's position covariance in world at
        those times, adds the drift of the poses that last saw each landmark (the map's world
        convention, :class:`reloc.backend.LandmarkMap`)."""
        recs = self.store.mapped()
        if not recs:
            return LandmarkMap.empty(self.kind)
        cov = np.array([r.cov_world_m2 for r in recs])
        if pose_cov_at is not None:
            cov = cov + pose_cov_at(np.array([r.t_last for r in recs]))
        return LandmarkMap(
            ids=np.array([r.lid for r in recs], dtype=int),
            xyz_world_m=np.array([r.xyz_world_m for r in recs]),
            cov_world_m2=cov,
            size_m=np.array([r.size_sum_m / max(r.n_obs, 1) for r in recs]),
            n_obs=np.array([r.n_obs for r in recs], dtype=int),
            kind=self.kind,
            catalog_row=np.array([self.anchored.get(r.lid, -1) for r in recs], dtype=int) if self.anchored else None,
        )

    def stats(self) -> dict:
        return {"n_frames_skipped": self.n_frames_skipped, "n_budget_skipped": self.store.n_budget_skipped,
                "n_budget_new_skipped": self.store.n_budget_new_skipped, "n_not_persistent": self.store.n_not_persistent,
                "n_jc_dropped": self.store.n_jc_dropped}

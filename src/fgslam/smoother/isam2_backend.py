"""``Isam2Smoother``: the GTSAM iSAM2 back-end behind the shared :class:`reloc.backend.Backend`
protocol.

Reads like the algorithm: odometry steps accumulate between keyframes (``predict``); a keyframe
adds a between-factor, a gravity factor and the rock factors buffered since the previous one, in
one iSAM2 update; rock frames associate detections with the map through the shared front-end
(``update_landmarks``); a late global fix lands on the keyframe before its ``t_meas`` through the
odometry in between, is gated, robustly weighted, and retracted if its residual stays large
(``apply_fix``).
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import C, L, X

from fgslam.errors import SmootherError
from fgslam.smoother.config import SmootherConfig
from fgslam.smoother.factors import (
    adjoint,
    cov_gtsam_to_world,
    cov_world_to_gtsam,
    inverse,
    make_calibrated_point_factor,
    make_point_factor,
)
from fgslam.smoother.fixes import FixRecord, innovation_d2, place_fix, residual_d2_many
from fgslam.smoother.keyframes import KeyframeStore, keyframe_due
from fgslam.smoother.landmarks import ACTIVE, LandmarkStore
from fgslam.smoother.odometry_factors import OdometryAccumulator, between_factor, gravity_factor
from fgslam.smoother.solver import Solver, SolverUpdateError
from reloc.backend import (
    BackendStats,
    FixOutcome,
    LandmarkMap,
    LandmarkUpdateReport,
    PoseEstimate,
    Trajectory,
)
from reloc.calibration import calibration_report
from reloc.geometry import skew
from reloc.measurements import GlobalFix, RockObservations
from reloc.odometry import OdometryStep

log = logging.getLogger(__name__)


def _pose_cov_prior(initial: PoseEstimate) -> np.ndarray:
    C = cov_world_to_gtsam(initial.T_world_base[:3, :3], np.asarray(initial.cov, dtype=float))
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    return (V * np.maximum(w, 1e-10)) @ V.T


class Isam2Smoother:
    """iSAM2 (or fixed-lag) smoother of keyframe poses ``X(i)`` and rock landmarks ``L(j)``."""

    name = "isam2"

    def __init__(self, initial: PoseEstimate, config: SmootherConfig | None = None) -> None:
        T0, C0 = np.asarray(initial.T_world_base, dtype=float), np.asarray(initial.cov, dtype=float)
        if T0.shape != (4, 4) or C0.shape != (6, 6) or not (np.all(np.isfinite(T0)) and np.all(np.isfinite(C0))):
            raise SmootherError(
                f"initial PoseEstimate needs a finite T_world_base (4, 4) and cov (6, 6), got {T0.shape} / {C0.shape}"
            )
        if np.abs(T0[:3, :3] @ T0[:3, :3].T - np.eye(3)).max() > 1e-6:
            raise SmootherError("initial PoseEstimate.T_world_base has no valid rotation block")
        self.cfg = config or SmootherConfig()
        self.solver = Solver(self.cfg)
        self.kfs = KeyframeStore()
        self.landmarks = LandmarkStore(self.cfg.landmarks)
        self.fixes: list[FixRecord] = []
        self.update_latency_s: list[float] = []  # wall time of each keyframe / fix update
        self.update_cpu_s: list[float] = []  # CPU time of the same (robust to a loaded machine)
        self.n_predict = self.n_frames = self.n_frames_skipped = self.n_failed_updates = 0
        self.n_fix_ok = self.n_fix_rejected = 0
        self._stamps: dict[int, float] = {}  # fixed-lag key timestamps (s)
        self._buf_graph = gtsam.NonlinearFactorGraph()
        self._buf_values = gtsam.Values()
        self._buf_lids: set[int] = set()
        self._seen_on_kf: set[int] = set()
        self._last_frame_t = -np.inf
        self._solver_touched = False

        k = self.kfs.add(initial.t)
        graph = gtsam.NonlinearFactorGraph()
        prior = gtsam.noiseModel.Gaussian.Covariance(_pose_cov_prior(initial))
        graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(initial.T_world_base), prior))
        values = gtsam.Values()
        values.insert(X(k), gtsam.Pose3(initial.T_world_base))
        self._stamps[X(k)] = initial.t
        cal = self.cfg.calibration
        self.calibrated = cal.enabled
        if self.calibrated:  # C(0): rotation error (3) and scale - 1 of the rock measurements
            sig = np.maximum(cal.prior_sigmas(), 1e-6)  # (a sigma of 0: held at 0 by a stiff prior)
            graph.add(gtsam.PriorFactorVector(C(0), np.zeros(4), gtsam.noiseModel.Diagonal.Sigmas(sig)))
            values.insert(C(0), np.zeros(4))
        self.solver.update(graph, values, {X(k): initial.t})
        self.acc = OdometryAccumulator(initial.t)
        self.segments: dict[int, OdometryAccumulator] = {k: self.acc}
        self._refresh_latest()

    # ------------------------------------------------------------------ protocol
    def predict(self, step: OdometryStep) -> None:
        """Accumulate one odometry step; start a keyframe (one iSAM2 update) when one is due."""
        if step.t1 <= self.acc.t_now:  # entirely before the current state (e.g. before the start pose)
            log.debug("odometry step ending at %.3f s ignored: state is at %.3f s", step.t1, self.acc.t_now)
            return
        self.n_predict += 1
        self.acc.push(step, self.cfg.odometry)
        if keyframe_due(self.acc, self.cfg.keyframes):
            t0, c0 = time.perf_counter(), time.thread_time()
            self._add_keyframe()
            self.update_latency_s.append(time.perf_counter() - t0)
            self.update_cpu_s.append(time.thread_time() - c0)

    def update_landmarks(self, obs: RockObservations) -> LandmarkUpdateReport:
        """Associate one rock frame; buffer factors on the current keyframe for the next update."""
        n = len(obs)
        if n == 0 or obs.t - self._last_frame_t < self.cfg.landmarks.min_frame_interval_s:
            self.n_frames_skipped += int(n > 0)
            return LandmarkUpdateReport(obs.t, n, 0, 0, 0)
        self.n_frames += 1
        self._last_frame_t = obs.t
        kf = len(self.kfs) - 1
        T_rel, C_rel = self.acc.T_kf_now, self.acc.cov
        R_rel = T_rel[:3, :3]
        z = np.asarray(obs.xyz_base_m)
        Rz = np.asarray(obs.cov_base_m2) * self.cfg.landmarks.rock_cov_scale
        # the observation moved onto the keyframe through the odometry since it
        z_kf = z @ R_rel.T + T_rel[:3, 3]
        J = np.zeros((n, 3, 6))
        J[:, :, :3] = -R_rel @ skew(z)
        J[:, :, 3:] = R_rel
        R_kf = R_rel @ Rz @ R_rel.T + J @ C_rel @ np.swapaxes(J, 1, 2)
        fa = self.landmarks.associate_frame(
            obs.t, kf, self.T_kf @ T_rel, C_rel, z, Rz, np.asarray(obs.size_m), z_kf, R_kf
        )
        for lid, zk, Rk in fa.observed:
            if lid in self._seen_on_kf:
                continue
            self._seen_on_kf.add(lid)
            self._buf_graph.add(self._point_factor(kf, lid, zk, Rk))
            self._buf_lids.add(lid)
        for rec in fa.to_insert:
            rec.status = ACTIVE
            self._buf_values.insert(L(rec.lid), np.asarray(rec.xyz_world_m, dtype=float))
            self._buf_lids.add(rec.lid)
            self._seen_on_kf.add(rec.lid)
            for kf_i, zk, Rk in rec.pending:
                self._buf_graph.add(self._point_factor(kf_i, rec.lid, zk, Rk))
            rec.pending = []
        return LandmarkUpdateReport(obs.t, n, fa.n_associated, fa.n_new, fa.n_rejected)

    def _point_factor(self, kf: int, lid: int, z_kf: np.ndarray, R_kf: np.ndarray):
        k = self.cfg.landmarks.huber_k
        if self.calibrated:
            return make_calibrated_point_factor(X(kf), L(lid), C(0), z_kf, R_kf, k)
        return make_point_factor(X(kf), L(lid), z_kf, R_kf, k)

    def calibration(self) -> dict:
        """The estimated stereo calibration (empty without the calibration variable): rotation
        vector (deg, base_link) and range scale, with their marginal sigmas."""
        if not self.calibrated:
            return {}
        c = np.asarray(self.solver.isam.calculateEstimateVector(C(0)))
        sig = np.sqrt(np.diag(self.solver.marginal_cov(C(0))))
        return calibration_report(c[:3], 1.0 + float(c[3]), sig[:3], sig[3])

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        """Place a (late) planar fix on the keyframe before ``t_meas``; gate, update, retract."""
        t0, c0 = time.perf_counter(), time.thread_time()
        self._solver_touched = False
        outcome = self._apply_fix(fix)
        if self._solver_touched:  # gate rejections cost microseconds and are not updates
            self.update_latency_s.append(time.perf_counter() - t0)
            self.update_cpu_s.append(time.thread_time() - c0)
        if outcome.accepted:
            self.n_fix_ok += 1
        else:
            self.n_fix_rejected += 1
            log.info("fix at t=%.2f rejected: %s", fix.t_meas, outcome.reason)
        return outcome

    def estimate(self) -> PoseEstimate:
        """Latest pose: keyframe estimate composed with the odometry since, covariance propagated."""
        T = self.T_kf @ self.acc.T_kf_now
        Ad = adjoint(inverse(self.acc.T_kf_now))
        C = Ad @ self.cov_kf @ Ad.T + self.acc.cov
        return PoseEstimate(self.acc.t_now, T, cov_gtsam_to_world(T[:3, :3], C))

    def landmark_map(self) -> LandmarkMap:
        """Landmarks in the graph (and those retired from the fixed-lag window), world frame."""
        recs = self.landmarks.mapped()
        if not recs:
            return LandmarkMap.empty()
        return LandmarkMap(
            ids=np.array([r.lid for r in recs], dtype=int),
            xyz_world_m=np.array([r.xyz_world_m for r in recs]),
            cov_world_m2=np.array([r.cov_world_m2 for r in recs]),
            size_m=np.array([r.size_sum_m / max(r.n_obs, 1) for r in recs]),
            n_obs=np.array([r.n_obs for r in recs], dtype=int),
        )

    def trajectory(self) -> Trajectory:
        """Smoothed keyframe poses with marginal covariances (protocol convention)."""
        n = len(self.kfs)
        live = [i for i in range(n) if i not in self.kfs.frozen and self.solver.alive(X(i))]
        covs = dict(zip(live, self.solver.marginal_covs([X(i) for i in live])))
        Ts, Cs = [], []
        for i in range(n):
            if i in self.kfs.frozen:
                T, C = self.kfs.frozen[i]
            elif i not in covs:  # marginalized without being frozen: causal estimate
                T, C = self.kfs.online_T[i], self.kfs.online_cov[i]
            else:
                T = self.solver.pose(X(i))
                C = cov_gtsam_to_world(T[:3, :3], covs[i])
            Ts.append(T)
            Cs.append(C)
        return Trajectory(np.array(self.kfs.t), np.array(Ts), np.array(Cs))

    def online_trajectory(self) -> Trajectory:
        """Causal estimate at each keyframe, as it was right after that keyframe's update."""
        n = len(self.kfs.online_T)
        return Trajectory(np.array(self.kfs.t[:n]), np.array(self.kfs.online_T), np.array(self.kfs.online_cov))

    def stats(self) -> BackendStats:
        """Counters, latencies (whole keyframe / fix processing, ms) and the list of retracted fixes."""
        lat = np.array(self.update_latency_s) if self.update_latency_s else np.zeros(1)
        retracted = [
            {"t_meas": r.fix.t_meas, "x_m": r.fix.x_m, "y_m": r.fix.y_m, "reason": r.retracted_reason}
            for r in self.fixes if r.retracted_reason
        ]
        return BackendStats(
            n_predict=self.n_predict,
            n_landmark_frames=self.n_frames,
            n_fixes_accepted=self.n_fix_ok,
            n_fixes_rejected=self.n_fix_rejected,
            n_landmarks=len(self.landmarks.mapped()),
            extra={
                "n_keyframes": len(self.kfs),
                "n_updates": len(self.update_latency_s),
                "latency_median_ms": float(np.median(lat) * 1e3),
                "latency_p99_ms": float(np.percentile(lat, 99) * 1e3),
                "n_failed_updates": self.n_failed_updates,
                "n_recoveries": self.solver.n_recoveries,
                "factorization": self.solver.factorization.value,
                "n_frames_skipped": self.n_frames_skipped,
                "n_budget_skipped": self.landmarks.n_budget_skipped,
                "n_budget_new_skipped": self.landmarks.n_budget_new_skipped,
                "retracted_fixes": retracted,
                "fixed_lag_s": self.cfg.fixed_lag_s,
                **({"calibration": self.calibration()} if self.calibrated else {}),
            },
        )

    # ------------------------------------------------------------------ internals
    def _timed_update(self, graph, values, stamps=None, remove=None, keep_latest_root=False) -> list[int]:
        self._solver_touched = True
        return self.solver.update(graph, values, stamps, remove, self._latest_keys() if keep_latest_root else ())

    def _latest_keys(self) -> tuple[int, ...]:
        """The two newest keyframes, to be eliminated last (see :meth:`Solver.update`)."""
        k = len(self.kfs) - 1
        return (X(k - 1), X(k)) if k > 0 else (X(k),)

    def _add_keyframe(self) -> None:
        """New keyframe X(k) at the accumulator's time: odometry, gravity and buffered rock factors."""
        acc, k_prev = self.acc, len(self.kfs) - 1
        k = self.kfs.add(acc.t_now)
        t = acc.t_now
        odo = gtsam.NonlinearFactorGraph()
        odo.add(between_factor(X(k_prev), X(k), acc.T_kf_now, acc.cov))
        if acc.R_ref_base is not None:
            odo.add(gravity_factor(X(k), acc.R_ref_base, self.cfg.odometry.gravity_sigma_rad))
        vals = gtsam.Values()
        vals.insert(X(k), gtsam.Pose3(self.T_kf @ acc.T_kf_now))
        stamps = {X(k): t}
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(odo)
        graph.push_back(self._buf_graph)
        full_vals = gtsam.Values(vals)
        full_vals.insert(self._buf_values)
        full_stamps = dict(stamps)
        full_stamps.update({L(lid): t for lid in self._buf_lids})
        if self.solver.fixed_lag:
            self._before_marginalization(t, full_stamps)
        try:
            self._timed_update(graph, full_vals, full_stamps)
            self._stamps.update(full_stamps)
        except SolverUpdateError as exc:
            # keep the keyframe chain alive: retry with odometry only, drop the rock batch
            self.n_failed_updates += 1
            log.warning("keyframe %d update failed (%s); retrying without rock factors", k, exc)
            for key in self._buf_values.keys():  # noqa: SIM118 (gtsam.Values)
                self.landmarks.drop(int(gtsam.Symbol(key).index()))
            self._timed_update(odo, vals, stamps)
            self._stamps.update(stamps)
        self._buf_graph = gtsam.NonlinearFactorGraph()
        self._buf_values = gtsam.Values()
        self._buf_lids = set()
        self._seen_on_kf = set()
        self.acc = OdometryAccumulator(t)
        self.segments[k] = self.acc
        self._prune_history(t)
        self._refresh_latest()

    def _before_marginalization(self, t: float, new_stamps: dict[int, float]) -> None:
        """Fixed-lag: freeze the estimates of keys that the coming update will marginalize."""
        horizon = t - self.cfg.fixed_lag_s
        stamps = dict(self._stamps)
        stamps.update(new_stamps)
        for key, ts in stamps.items():
            if ts >= horizon or not self.solver.alive(key):
                continue
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("x"):
                i = int(sym.index())
                T = self.solver.pose(key)
                if self.cfg.frozen_marginals:
                    C = cov_gtsam_to_world(T[:3, :3], self.solver.marginal_cov(key))
                else:  # the causal covariance: an upper bound, and free
                    C = self.kfs.online_cov[i]
                self.kfs.frozen[i] = (T, C)
            else:
                rec = self.landmarks.records.get(int(sym.index()))
                if rec is not None:
                    rec.xyz_world_m = self.solver.point(key)
                    self.landmarks.retire(rec.lid)
            del self._stamps[key]
        oldest = self.kfs.before(horizon + self.cfg.fixes.window_margin_s) + 1
        self.landmarks.prune_candidates(t, oldest)

    def _prune_history(self, t: float) -> None:
        """Drop odometry history older than fixes may be (bounded memory)."""
        for k in [k for k in self.segments if self.segments[k].t_now < t - self.cfg.fixes.max_age_s]:
            del self.segments[k]
        if not self.solver.fixed_lag:
            self.landmarks.prune_candidates(t, 0)

    def _refresh_latest(self) -> None:
        """Cache the newest keyframe's estimate/marginal, record the causal estimate, and pull the
        solver's positions of the landmarks near the rover."""
        k = len(self.kfs) - 1
        self.T_kf = self.solver.pose(X(k))
        self.cov_kf = self.solver.marginal_cov(X(k))
        if len(self.kfs.online_T) <= k:
            self.kfs.record_online(self.T_kf, cov_gtsam_to_world(self.T_kf[:3, :3], self.cov_kf))
        self.landmarks.set_view_cache(self.T_kf[:3, 3])
        for rec in self.landmarks.in_view(self.T_kf[:3, :3], self.T_kf[:3, 3]):
            if rec.status == ACTIVE and self.solver.alive(L(rec.lid)):
                rec.xyz_world_m = self.solver.point(L(rec.lid))

    def _apply_fix(self, fix: GlobalFix) -> FixOutcome:
        cfg = self.cfg.fixes
        k = self.kfs.before(fix.t_meas)
        if k < 0:
            return FixOutcome(fix, False, "t_meas is before the first keyframe")
        if fix.t_meas > self.acc.t_now + 0.1:
            return FixOutcome(fix, False, f"t_meas {fix.t_meas:.2f} s is ahead of the odometry ({self.acc.t_now:.2f} s)")
        seg = self.segments.get(k)
        if seg is None:
            return FixOutcome(fix, False, f"older than the odometry history ({cfg.max_age_s:.0f} s)")
        if self.solver.fixed_lag and (
            not self.solver.alive(X(k)) or self.kfs.t[k] < self.kfs.t[-1] - self.cfg.fixed_lag_s + cfg.window_margin_s
        ):
            return FixOutcome(fix, False, f"older than the smoother window ({self.cfg.fixed_lag_s:.0f} s)")
        T_rel, C_rel = seg.at(fix.t_meas)
        T_kf = self.solver.pose(X(k))
        yaw_floor = cfg.calibrated_yaw_sigma_floor_rad if self.calibrated else 0.0
        factor, cov_res = place_fix(fix, X(k), T_rel, C_rel, T_kf, cfg.cauchy_k, yaw_floor)
        if cfg.gate_smoothed_marginal:
            cov_kf = self.solver.marginal_cov(X(k))
        else:  # causal covariance of the keyframe: an upper bound of its smoothed marginal, free
            cov_kf = cov_world_to_gtsam(T_kf[:3, :3], self.kfs.online_cov[k])
        d2, dist = innovation_d2(fix, T_kf, cov_kf, T_rel, cov_res)
        if dist > cfg.gate_distance_m:
            return FixOutcome(fix, False, f"distance gate {dist:.1f} m > {cfg.gate_distance_m:.1f} m", d2)
        if d2 > cfg.gate_chi2:
            return FixOutcome(fix, False, f"Mahalanobis gate d2 {d2:.1f} > {cfg.gate_chi2:.1f}", d2)
        snap = self.solver.snapshot() if self.cfg.snapshot_before_fixes else None
        alive = set(self.solver._alive)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(factor)
        try:
            idx = self._timed_update(graph, gtsam.Values(), keep_latest_root=True)
            self.solver.extra_iterations(cfg.extra_iterations, self._latest_keys())
        except (SolverUpdateError, RuntimeError, ValueError) as exc:
            self.solver.restore(snap, alive)
            self.n_failed_updates += 1
            return FixOutcome(fix, False, f"solver update failed: {exc}", d2)
        rec = FixRecord(fix, k, X(k), T_rel, cov_res, idx[0])
        self.fixes.append(rec)
        self._retract_outliers()
        self._refresh_latest()
        if not rec.active:
            return FixOutcome(fix, False, rec.retracted_reason, d2)
        return FixOutcome(fix, True, "", d2)

    def _retract_outliers(self) -> None:
        """Remove, worst first, fixes whose residual stays above ``retract_chi2`` after optimisation."""
        cfg = self.cfg.fixes
        for _ in range(3):
            live = [r for r in self.fixes if r.active and self.solver.alive(r.key)]
            if not live:
                return
            d2 = residual_d2_many(live, np.array([self.solver.pose(r.key) for r in live]))
            worst = int(np.argmax(d2))
            if d2[worst] <= cfg.retract_chi2:
                return
            rec = live[worst]
            try:
                self._timed_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), remove=[rec.factor_index], keep_latest_root=True)
                self.solver.extra_iterations(cfg.extra_iterations, self._latest_keys())
            except (SolverUpdateError, RuntimeError, ValueError) as exc:
                log.warning("could not retract fix at t=%.2f: %s", rec.fix.t_meas, exc)
                return
            self._remap_indices()
            rec.active = False
            rec.retracted_reason = f"retracted: residual d2 {d2[worst]:.1f} > {cfg.retract_chi2:.1f} after optimisation"
            log.info("fix at t=%.2f %s", rec.fix.t_meas, rec.retracted_reason)

    def _remap_indices(self) -> None:
        m = self.solver.take_index_map()
        if m:
            for r in self.fixes:
                if r.active:
                    r.factor_index = m.get(r.factor_index, r.factor_index)


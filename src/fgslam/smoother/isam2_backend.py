"""``Isam2Smoother``: the GTSAM iSAM2 back-end behind the shared :class:`reloc.backend.Backend`
protocol.

Reads like the algorithm: odometry steps accumulate between keyframes (``predict``); a keyframe
adds a between-factor, a gravity factor and the landmark factors buffered since the previous one,
in one iSAM2 update; landmark frames of every kind go to that kind's layer (``observe``,
:mod:`fgslam.smoother.kinds`; rocks: :mod:`fgslam.smoother.rocks`), which associates them with its
map and buffers their factors; a late global fix lands on the keyframe before its ``t_meas``
through the odometry in between, is gated, robustly weighted, and retracted if its residual stays
large (``apply_fix``, the stage in :mod:`fgslam.smoother.fix_updates`).
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, C, G, X

from fgslam.errors import SmootherError
from fgslam.smoother.config import SmootherConfig
from fgslam.smoother.factors import adjoint, cov_gtsam_to_world, cov_world_to_gtsam, inverse
from fgslam.smoother.fix_offsets import FixOffsets
from fgslam.smoother.fix_updates import WINDOW_REASON, LateFixes
from fgslam.smoother.fixes import FixRecord
from fgslam.smoother.keyframes import KeyframeStore, keyframe_due
from fgslam.smoother.kinds import (
    OFFSET_SYMBOL,
    POSE_SYMBOL,
    SLIP_SYMBOL,
    YAW_BIAS_SYMBOL,
    KeyframeFrame,
    SmootherKinds,
    resolved_smoother_config,
    symbol_of,
)
from fgslam.smoother.odometry_factors import (
    OdometryAccumulator,
    corrected_motion,
    gravity_factor,
    odometry_factor,
    random_walk_factor,
)
from fgslam.smoother.solver import Solver, SolverUpdateError
from reloc.backend import (
    Backend,
    BackendStats,
    FixOutcome,
    LandmarkMap,
    LandmarkUpdateReport,
    PoseEstimate,
    Trajectory,
)
from reloc.calibration import calibration_report
from reloc.covariance import psd_part
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep

log = logging.getLogger(__name__)


def _pose_cov_prior(initial: PoseEstimate) -> np.ndarray:
    return psd_part(cov_world_to_gtsam(initial.T_world_base[:3, :3], np.asarray(initial.cov, dtype=float)), 1e-10)


class Isam2Smoother(LateFixes, Backend):
    """iSAM2 (or fixed-lag) smoother of keyframe poses ``X(i)`` and the landmarks of every kind
    (rocks ``L(j)``)."""

    name = "isam2"
    relative_cost = 2.0  # fixed-lag, the demo: ~150 s against the EKF's ~77 s

    def __init__(self, initial: PoseEstimate, config: SmootherConfig | None = None) -> None:
        T0, C0 = np.asarray(initial.T_world_base, dtype=float), np.asarray(initial.cov, dtype=float)
        if T0.shape != (4, 4) or C0.shape != (6, 6) or not (np.all(np.isfinite(T0)) and np.all(np.isfinite(C0))):
            raise SmootherError(
                f"initial PoseEstimate needs a finite T_world_base (4, 4) and cov (6, 6), got {T0.shape} / {C0.shape}"
            )
        if np.abs(T0[:3, :3] @ T0[:3, :3].T - np.eye(3)).max() > 1e-6:
            raise SmootherError("initial PoseEstimate.T_world_base has no valid rotation block")
        self.config = config or SmootherConfig()
        self.solver = Solver(self.config)
        self.solver.on_rebuild = self._remap_fix_factors
        self.kfs = KeyframeStore()
        self.fixes: list[FixRecord] = []
        self.offsets = FixOffsets(self.config.fixes)  # the fix sources' shared errors (correlation_model "bias")
        self.update_latency_s: list[float] = []  # wall time of each keyframe / fix update
        self.update_cpu_s: list[float] = []  # CPU time of the same (robust to a loaded machine)
        self.n_predict = self.n_failed_updates = 0
        self.n_fix_ok = self.n_fix_rejected = 0
        self.n_heights_refused = 0  # fixes placed without their height (FixConfig.height_gate_chi2)
        self.n_anchor_fixes = self.n_anchors = 0  # fixes applied as priors on their landmarks, and those landmarks
        self.fix_reject_reasons: dict[str, int] = {}  # rejected fixes by the reason's first word
        self._stamps: dict[int, float] = {}  # fixed-lag key timestamps (s)
        self._buf_graph = gtsam.NonlinearFactorGraph()
        self._buf_values = gtsam.Values()
        self._solver_touched = False
        self._growth_kf, self._growth = -1, {}  # cov_growth cache: keyframe index -> (6, 6)
        self._growth_t = np.zeros(0)  # the keyframe times the cache was made with

        k = self.kfs.add(initial.t)
        graph = gtsam.NonlinearFactorGraph()
        prior = gtsam.noiseModel.Gaussian.Covariance(_pose_cov_prior(initial))
        graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(initial.T_world_base), prior))
        values = gtsam.Values()
        values.insert(X(k), gtsam.Pose3(initial.T_world_base))
        self._stamps[X(k)] = stamp0 = self._stamp(initial.t)
        cal = self.config.calibration
        self.calibrated = cal.enabled and self.config.calibration_mode == "estimate"  # "consider": no C(0)
        if self.calibrated:  # C(0): rotation error (3) and scale - 1 of the rock measurements
            sig = np.maximum(cal.prior_sigmas(), 1e-6)  # (a sigma of 0: held at 0 by a stiff prior)
            graph.add(gtsam.PriorFactorVector(C(0), np.zeros(4), gtsam.noiseModel.Diagonal.Sigmas(sig)))
            values.insert(C(0), np.zeros(4))
        stamps = {X(k): stamp0}
        odo = self.config.odometry
        self.slip_on = odo.slip_sigma > 0  # G(i): the wheels' slip from keyframe i on
        self.bias_on = odo.yaw_rate_bias_sigma_radps > 0  # B(i): the IMU's yaw-rate bias from keyframe i on
        self._slip = self._bias = 0.0  # their latest estimates
        for on, key, sigma in ((self.slip_on, G(k), odo.slip_sigma), (self.bias_on, B(k), odo.yaw_rate_bias_sigma_radps)):
            if on:
                graph.add(gtsam.PriorFactorDouble(key, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma)))
                values.insert(key, 0.0)
                stamps[key] = stamp0
        self.solver.update(graph, values, stamps)
        self.kinds = SmootherKinds(self.config, C(0) if self.calibrated else None)
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
        self.acc.push(step, self.config.odometry)
        if keyframe_due(self.acc, self.config.keyframes):
            t0, c0 = time.perf_counter(), time.thread_time()
            self._add_keyframe()
            self.update_latency_s.append(time.perf_counter() - t0)
            self.update_cpu_s.append(time.thread_time() - c0)

    def observe(self, obs) -> LandmarkUpdateReport:
        """One frame of a registered landmark kind: its layer associates it and buffers factors on
        the current keyframe for the next update."""
        frame = KeyframeFrame(len(self.kfs) - 1, self.T_kf, self._motion_since_kf(), self.acc.cov,
                              self._buf_graph, self._buf_values, self._cov_growth)
        return self.kinds.for_obs(obs).observe(obs, frame)

    @classmethod
    def resolved_config(cls, config: SmootherConfig) -> dict:
        """The resolved config, with every registered kind's resolved smoother settings in ``kinds``."""
        return resolved_smoother_config(config)

    def calibration(self) -> dict:
        """The estimated stereo calibration (empty without the calibration variable): rotation
        vector (deg, base_link) and range scale, with their marginal sigmas."""
        if not self.calibrated:
            return {}
        s = self.solver.ifls if self.solver.fixed_lag else self.solver.isam
        c = np.asarray(s.calculateEstimateVector(C(0)))
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
            key = outcome.reason.split(" ")[0] if outcome.reason else "unknown"
            self.fix_reject_reasons[key] = self.fix_reject_reasons.get(key, 0) + 1
            log.info("fix at t=%.2f rejected: %s", fix.t_meas, outcome.reason)
        return outcome

    def estimate(self) -> PoseEstimate:
        """Latest pose: keyframe estimate composed with the odometry since, covariance propagated."""
        T = self.T_kf @ self._motion_since_kf()
        return PoseEstimate(self.acc.t_now, T, cov_gtsam_to_world(T[:3, :3], self._predicted_cov(self.acc)))

    def _cov_growth(self, t_last: np.ndarray) -> np.ndarray:
        """(K, 6, 6) GTSAM body frame: how much more uncertain the newest keyframe is than the
        keyframe at or before each time ``t_last`` (K,) was, from the causal covariances (the
        positive part of the difference; 0 for the newest keyframe itself). It is the pose's
        uncertainty relative to a landmark last seen then, which the landmark store's covariance
        (relative to its observing poses) leaves out: after a blackout of the camera it is the
        drift while blind. Cached per keyframe."""
        k_now = len(self.kfs) - 1
        if self._growth_kf != k_now:  # a new keyframe: the keyframe times once, the growths afresh
            self._growth_kf, self._growth, self._growth_t = k_now, {}, self.kfs.t
        idx = np.clip(np.searchsorted(self._growth_t, t_last, side="right") - 1, 0, k_now)
        out = np.zeros((len(idx), 6, 6))
        used = [int(i) for i in np.unique(idx) if i != k_now]
        new = [i for i in used if i not in self._growth]
        if new:  # one batched eigen-decomposition for the keyframes not cached yet
            C_now = self.kfs.online_cov(k_now)
            G = cov_world_to_gtsam(self.T_kf[:3, :3], psd_part(C_now - np.array([self.kfs.online_cov(i) for i in new])))
            self._growth.update(zip(new, G))
        for i in used:
            out[idx == i] = self._growth[i]
        return out

    def _motion_since_kf(self, acc: OdometryAccumulator | None = None, T_rel: np.ndarray | None = None,
                         t: float | None = None) -> np.ndarray:
        """(4, 4) motion since the keyframe of ``acc`` (default: the newest) to its end (or ``T_rel``
        at ``t``), corrected by the latest slip and yaw-rate bias estimates when they are variables."""
        acc = acc or self.acc
        T = acc.T_kf_now if T_rel is None else T_rel
        if not (self.slip_on or self.bias_on):
            return T
        dt = (acc.t_now if t is None else t) - acc.t_kf
        k = self.kfs.before(acc.t_kf + 1e-9)
        return corrected_motion(T, self._slip, self._bias * dt, self.kfs.online_T(k)[:3, :3])

    def _predicted_cov(self, acc: OdometryAccumulator) -> np.ndarray:
        """The newest keyframe's marginal moved through the odometry ``acc`` since it (GTSAM tangent)."""
        Ad = adjoint(inverse(acc.T_kf_now))
        return Ad @ self.cov_kf @ Ad.T + acc.cov

    def landmark_map(self, kind: str) -> LandmarkMap:
        """Landmarks of ``kind`` in the graph (and those retired from the fixed-lag window), world
        frame; empty for a kind not observed yet."""
        layer = self.kinds.named(kind)
        return LandmarkMap.empty(kind) if layer is None else layer.landmark_map(self._position_cov_at)

    def _position_cov_at(self, t: np.ndarray) -> np.ndarray:
        """(K, 3, 3): the causal position covariance (world) of the latest keyframe at or before
        each of the times ``t`` (K,); zeros before the first."""
        n = self.kfs.n_online
        if not n:
            return np.zeros((len(t), 3, 3))
        i = np.searchsorted(self.kfs.t[:n], np.asarray(t, float), side="right") - 1
        used, where = np.unique(np.maximum(i, 0), return_inverse=True)
        out = np.array([self.kfs.online_cov(k)[:3, :3] for k in used])[where.reshape(-1)]
        out[i < 0] = 0.0
        return out

    def trajectory(self) -> Trajectory:
        """Smoothed keyframe poses with marginal covariances (protocol convention)."""
        n = len(self.kfs)
        live = [i for i in range(n) if not self.kfs.is_frozen(i) and self.solver.alive(X(i))]
        covs = dict(zip(live, self.solver.marginal_covs([X(i) for i in live])))
        Ts, Cs = [], []
        for i in range(n):
            if self.kfs.is_frozen(i):
                T, C = self.kfs.frozen(i)
            elif i not in covs:  # marginalized without being frozen: causal estimate
                T, C = self.kfs.online_T(i), self.kfs.online_cov(i)
            else:
                T = self.solver.pose(X(i))
                C = cov_gtsam_to_world(T[:3, :3], covs[i])
            Ts.append(T)
            Cs.append(C)
        return Trajectory(np.array(self.kfs.t), np.array(Ts), np.array(Cs))

    def online_trajectory(self) -> Trajectory:
        """Causal estimate at each keyframe, as it was right after that keyframe's update."""
        return Trajectory(*self.kfs.online_arrays())

    def stats(self) -> BackendStats:
        """Counters, latencies (whole keyframe / fix processing, ms) and the list of retracted fixes."""
        lat = np.array(self.update_latency_s) if self.update_latency_s else np.zeros(1)
        retracted = [
            {"t_meas": r.fix.t_meas, "x_m": r.fix.x_m, "y_m": r.fix.y_m, "reason": r.retracted_reason}
            for r in self.fixes if r.retracted_reason
        ]
        layers = self.kinds.used()
        kind_counts: dict[str, int] = {"n_frames_skipped": 0, "n_budget_skipped": 0, "n_budget_new_skipped": 0,
                                        "n_not_persistent": 0, "n_jc_dropped": 0}
        for layer in layers:
            for k, v in layer.stats().items():
                kind_counts[k] = kind_counts.get(k, 0) + v
        return BackendStats(
            n_predict=self.n_predict,
            n_landmark_frames=sum(layer.n_frames for layer in layers),
            n_fixes_accepted=self.n_fix_ok,
            n_fixes_rejected=self.n_fix_rejected,
            n_landmarks=sum(layer.n_landmarks for layer in layers),
            extra={
                "n_keyframes": len(self.kfs),
                "n_updates": len(self.update_latency_s),
                "latency_median_ms": float(np.median(lat) * 1e3),
                "latency_p99_ms": float(np.percentile(lat, 99) * 1e3),
                "n_failed_updates": self.n_failed_updates,
                "n_recoveries": self.solver.n_recoveries,
                "n_qr_retries": self.solver.n_qr_retries,
                "factorization": self.solver.factorization.value,
                "n_cholesky_returns": self.solver.n_cholesky_returns,
                "n_compactions": self.solver.n_compactions,
                **kind_counts,
                "retracted_fixes": retracted,
                "fix_reject_reasons": dict(self.fix_reject_reasons),
                "n_heights_refused": self.n_heights_refused,
                "n_anchor_fixes": self.n_anchor_fixes, "n_anchors": self.n_anchors,
                # fixes whose keyframe had left (or was about to leave) the fixed-lag window
                "n_fixes_older_than_window": self.fix_reject_reasons.get(WINDOW_REASON, 0),
                "fixed_lag_s": self.config.fixed_lag_s,
                **({"slip": self._scalar_report(G, self._slip)} if self.slip_on else {}),
                **({"yaw_rate_bias_deg_per_h": self._scalar_report(B, self._bias, np.degrees(3600.0))}
                   if self.bias_on else {}),
                **({"calibration": self.calibration()} if self.calibrated else {}),
                **({"fix_offset": self.offsets.report(self.solver.alive, self.solver.estimate, self.solver.marginal_cov),
                    "n_offset_restarts": self.offsets.n_restarts}
                   if self.config.fixes.correlation_model == "bias" else {}),
            },
        )

    def _scalar_report(self, symbol, estimate: float, unit: float = 1.0) -> dict:
        """The newest keyframe's estimate of a scalar variable (slip, yaw-rate bias) and its
        marginal sigma, times ``unit``."""
        key = symbol(len(self.kfs) - 1)
        sigma = float(np.sqrt(self.solver.marginal_cov(key)[0, 0])) if self.solver.alive(key) else float("nan")
        return {"estimate": round(estimate * unit, 5), "sigma": round(sigma * unit, 5)}

    # ------------------------------------------------------------------ internals
    def _timed_update(self, graph, values, stamps=None, remove=None, keep_latest_root=False) -> list[int]:
        self._solver_touched = True
        return self.solver.update(graph, values, stamps, remove, self._latest_keys() if keep_latest_root else ())

    def _latest_keys(self) -> tuple[int, ...]:
        """The two newest keyframes, to be eliminated last (see :meth:`Solver.update`)."""
        k = len(self.kfs) - 1
        return (X(k - 1), X(k)) if k > 0 else (X(k),)

    def _add_keyframe(self) -> None:
        """New keyframe X(k) at the accumulator's time: odometry, gravity and buffered landmark factors."""
        acc, k_prev = self.acc, len(self.kfs) - 1
        k = self.kfs.add(acc.t_now)
        t = acc.t_now
        odo = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        ts = self._stamp(t)
        stamps = {X(k): ts}
        # the slip and yaw-rate bias from the previous keyframe on correct its odometry; each
        # walks on to the new keyframe
        dt, cfg = t - self.kfs.t[k_prev], self.config.odometry
        odo.add(odometry_factor(X(k_prev), X(k), acc.T_kf_now, acc.cov, dt,
                                G(k_prev) if self.slip_on else None, B(k_prev) if self.bias_on else None))
        for on, sym, est, walk in ((self.slip_on, G, self._slip, cfg.slip_walk_rsqrt_s),
                                   (self.bias_on, B, self._bias, cfg.yaw_rate_bias_walk_radps_rsqrt_s)):
            if on:
                odo.add(random_walk_factor(sym(k_prev), sym(k), dt, walk))
                vals.insert(sym(k), est)
                stamps[sym(k)] = ts
        if acc.R_ref_base is not None:
            odo.add(gravity_factor(X(k), acc.R_ref_base, self.config.odometry.gravity_sigma_rad))
        vals.insert(X(k), gtsam.Pose3(self.T_kf @ self._motion_since_kf(acc)))
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(odo)
        graph.push_back(self._buf_graph)
        full_vals = gtsam.Values(vals)
        full_vals.insert(self._buf_values)
        full_stamps = dict(stamps)
        for layer in self.kinds.used():
            full_stamps.update(layer.buffered_stamps(ts))
        if self.solver.fixed_lag and self.calibrated:
            stamps[C(0)] = full_stamps[C(0)] = ts  # every rock factor uses it: it never leaves the window
        marginalizing = self.solver.fixed_lag and self._before_marginalization(ts, full_stamps)
        try:
            self._timed_update(graph, full_vals, full_stamps)
            self._stamps.update(full_stamps)
        except SolverUpdateError as exc:
            # keep the keyframe chain alive: retry with odometry only, drop the landmark batch
            self.n_failed_updates += 1
            log.warning("keyframe %d update failed (%s); retrying without landmark factors", k, exc)
            for key in self._buf_values.keys():  # noqa: SIM118 (gtsam.Values)
                self.kinds.for_key(key).drop(int(gtsam.Symbol(key).index()))
            self._timed_update(odo, vals, stamps)
            self._stamps.update(stamps)
        self._buf_graph = gtsam.NonlinearFactorGraph()
        self._buf_values = gtsam.Values()
        for layer in self.kinds.used():
            layer.on_keyframe()
        predicted = self._predicted_cov(acc) if marginalizing and self.config.predicted_cov_when_marginalizing else None
        self.acc = OdometryAccumulator(t)
        self.segments[k] = self.acc
        self._prune_history(t)
        self._refresh_latest(predicted)

    def _stamp(self, t: float) -> float:
        """The fixed-lag timestamp of a key made at ``t`` (see ``SmootherConfig.marginalize_every_s``)."""
        every = self.config.marginalize_every_s
        return float(np.floor(t / every) * every) if every > 0 else float(t)

    def _before_marginalization(self, t: float, new_stamps: dict[int, float]) -> bool:
        """Fixed-lag: freeze the estimates of keys that the coming update (newest stamp ``t``)
        will marginalize: those stamped before ``t - fixed_lag_s``. Whether there are any."""
        horizon = t - self.config.fixed_lag_s
        stamps = dict(self._stamps)
        stamps.update(new_stamps)
        leaving = False
        for key, ts in stamps.items():
            if ts >= horizon or not self.solver.alive(key):
                continue
            leaving = True
            i = int(gtsam.Symbol(key).index())
            if symbol_of(key) in (SLIP_SYMBOL, YAW_BIAS_SYMBOL, OFFSET_SYMBOL):
                pass  # they leave with their keyframe (an offset: the next fix of its source starts afresh)
            elif symbol_of(key) == POSE_SYMBOL:
                T = self.solver.pose(key)
                if self.config.frozen_marginals:
                    C = cov_gtsam_to_world(T[:3, :3], self.solver.marginal_cov(key))
                else:  # the causal covariance: an upper bound, and free
                    C = self.kfs.online_cov(i)
                self.kfs.freeze(i, T, C)
            else:  # a landmark of some kind (SmootherError for a key of no kind)
                self.kinds.for_key(key).marginalize(i, self.solver)
            del self._stamps[key]
        oldest = self.kfs.before(horizon + self.config.fixes.window_margin_s) + 1
        for layer in self.kinds.used():
            layer.prune(t, oldest)
        return leaving

    def _prune_history(self, t: float) -> None:
        """Drop odometry history older than fixes may be (bounded memory)."""
        for k in [k for k in self.segments if self.segments[k].t_now < t - self.config.fixes.max_age_s]:
            del self.segments[k]
        if not self.solver.fixed_lag:
            for layer in self.kinds.used():
                layer.prune(t, 0)

    def _refresh_latest(self, cov: np.ndarray | None = None) -> None:
        """Cache the newest keyframe's estimate and marginal (or ``cov``, GTSAM tangent, when
        given), record the causal estimate, and let each landmark kind pull the solver's
        estimates near the rover."""
        k = len(self.kfs) - 1
        self.T_kf = self.solver.pose(X(k))
        self.cov_kf = self.solver.marginal_cov(X(k)) if cov is None else cov
        if self.slip_on:
            self._slip = float(self.solver.estimate(G(k))[0])
        if self.bias_on:
            self._bias = float(self.solver.estimate(B(k))[0])
        if self.kfs.n_online <= k:
            self.kfs.record_online(self.T_kf, cov_gtsam_to_world(self.T_kf[:3, :3], self.cov_kf))
        for layer in self.kinds.used():
            layer.refresh(self.T_kf, self.solver)

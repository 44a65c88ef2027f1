"""The smoother's late-fix stage: a (late) global fix lands on the keyframe before its ``t_meas``
through the odometry in between, is gated, robustly weighted, applied in one iSAM2 update (the
two newest keyframes eliminated last), and retracted, worst first, if its residual stays large
after optimisation; with ``FixConfig.correlation_model`` "bias" it measures its source's shared
offset too (:mod:`fgslam.smoother.fix_offsets`). Mixed into
:class:`fgslam.smoother.isam2_backend.Isam2Smoother`, whose state (``config``, ``solver``, ``kfs``,
``segments``, ``acc``, ``fixes``, ``offsets``) it works on."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from fgslam.smoother.factors import cov_world_to_gtsam
from fgslam.smoother.fixes import FixRecord, innovation_d2, place_fix, residual_d2_many
from fgslam.smoother.solver import SolverUpdateError
from reloc.backend import FixOutcome
from reloc.measurements import GlobalFix

log = logging.getLogger("fgslam.smoother.isam2_backend")

WINDOW_REASON = "outside"  # first word of the reason of a fix refused by the fixed-lag window


class LateFixes:
    """``_apply_fix`` and the retraction of fixes (see module doc)."""

    def _apply_fix(self, fix: GlobalFix) -> FixOutcome:
        if fix.anchors and self.config.fixes.anchors:
            outcome = self._apply_anchors(fix)
            if outcome is not None:  # the entries on the landmarks; the height (if any) on the pose
                if outcome.accepted and fix.height is not None:
                    self._apply_pose_fix(fix.height_only())
                return outcome
        return self._apply_pose_fix(fix)

    def _apply_anchors(self, fix: GlobalFix) -> FixOutcome | None:
        """Put ``fix``'s catalog entries on its landmarks (``FixConfig.anchors``): a Gaussian prior
        on each landmark's (x, y) with the entry's covariance (nothing on z), in one update, gated on the
        squared Mahalanobis distance against the landmarks' marginals and on the distance gate.
        None when a landmark is not a variable of the solver (the fix is then taken as a pose)."""
        cfg = self.config.fixes
        keys, layers = [], []
        for a in fix.anchors:
            layer = self.kinds.named(a.kind)
            key = None if layer is None or not hasattr(layer, "anchor_key") else layer.anchor_key(a.landmark_id, self.solver)
            if key is None:
                return None
            keys.append(key)
            layers.append(layer)
        if any(a.landmark_id in layer.anchored for a, layer in zip(fix.anchors, layers)):
            return FixOutcome(fix, False, "anchored already: a landmark holds a catalog entry")
        xyz = [np.asarray(self.solver.point(k), float) for k in keys]
        nu = [a.xy_m - p[:2] for a, p in zip(fix.anchors, xyz)]
        dist = max(float(np.hypot(*v)) for v in nu)
        if dist > cfg.gate_distance_m:
            return FixOutcome(fix, False, f"distance gate (anchor) {dist:.1f} m > {cfg.gate_distance_m:.1f} m")
        d2 = sum(float(v @ np.linalg.solve(self.solver.marginal_cov(k)[:2, :2] + a.cov_xy, v))
                 for v, k, a in zip(nu, keys, fix.anchors))
        bound = cfg.anchor_chi2_per_dof * 2 * len(keys)
        if not d2 <= bound:
            return FixOutcome(fix, False, f"Mahalanobis gate (anchor) d2 {d2:.1f} > {bound:.1f}", d2)
        graph = gtsam.NonlinearFactorGraph()
        for a, k, p in zip(fix.anchors, keys, xyz):
            # Gaussian, not the fixes' Cauchy: the residual at the current estimate holds the
            # landmark's own uncertainty (gated above), which the entry's covariance does not, and
            # the kernel would take the drift it corrects for an outlier. The square-root
            # information has a zero row for z: the prior says nothing there (exactly, where a
            # large sigma would add a tiny information of its own)
            R = np.zeros((3, 3))
            R[:2, :2] = np.linalg.cholesky(np.linalg.inv(a.cov_xy)).T
            graph.add(gtsam.PriorFactorPoint3(k, gtsam.Point3(a.xy_m[0], a.xy_m[1], p[2]),
                                              gtsam.noiseModel.Gaussian.SqrtInformation(R)))
        idx, failure = self._fix_update(graph)
        if idx is None:
            return FixOutcome(fix, False, failure, d2)
        for a, layer in zip(fix.anchors, layers):
            layer.anchored[a.landmark_id] = a.catalog_row
        self.n_anchor_fixes += 1
        self.n_anchors += len(keys)
        self._refresh_latest()
        return FixOutcome(fix, True, "", d2)

    def _apply_pose_fix(self, fix: GlobalFix) -> FixOutcome:
        cfg = self.config.fixes
        k = self.kfs.before(fix.t_meas)
        if k < 0:
            return FixOutcome(fix, False, "t_meas is before the first keyframe")
        if fix.t_meas > self.acc.t_now + 0.1:
            return FixOutcome(fix, False, f"t_meas {fix.t_meas:.2f} s is ahead of the odometry ({self.acc.t_now:.2f} s)")
        seg = self.segments.get(k)
        if seg is None:
            return FixOutcome(fix, False, f"older than the odometry history ({cfg.max_age_s:.0f} s)")
        if self.solver.fixed_lag and (
            not self.solver.alive(X(k)) or self.kfs.t[k] < self.kfs.t[-1] - self.config.fixed_lag_s + cfg.window_margin_s
        ):
            return FixOutcome(fix, False, f"{WINDOW_REASON} the smoother window: t_meas {fix.t_meas:.1f} s is older than "
                              f"the {self.config.fixed_lag_s:.0f} s window less its {cfg.window_margin_s:.0f} s margin")
        T_rel, C_rel = seg.at(fix.t_meas)
        T_rel = self._motion_since_kf(seg, T_rel, fix.t_meas)
        T_kf = self.solver.pose(X(k))
        yaw_floor = cfg.calibrated_yaw_sigma_floor_rad if self.calibrated else 0.0
        # the kernel in the innovation's sigmas: the keyframe's causal covariance (fixed when it was added)
        est_xy = self.kfs.online_cov(k)[:2, :2] if cfg.kernel_on_innovation else None
        plan = None
        if self.offsets.applies(fix):  # where the estimate is now: the distance since the source's last fix
            plan = self.offsets.plan(fix, (self.T_kf @ self._motion_since_kf())[:2, 3], self.solver.alive,
                                     self.solver.estimate)

        def place(f: GlobalFix):  # the same placement and kernel for the fix and its planar part
            if plan is None:
                return place_fix(f, X(k), T_rel, C_rel, T_kf, cfg.cauchy_k, yaw_floor, est_xy, cfg.kernel_widen_above)
            w = plan.white if f.height is not None else plan.white.planar()  # its unshared noise
            return place_fix(w, X(k), T_rel, C_rel, T_kf, cfg.cauchy_k, yaw_floor, est_xy, cfg.kernel_widen_above,
                             (plan.key, plan.G[:len(w.measured)]))

        factor, cov_res = place(fix)
        if cfg.gate_smoothed_marginal:
            cov_kf = self.solver.marginal_cov(X(k))
        else:  # causal covariance of the keyframe: an upper bound of its smoothed marginal, free
            cov_kf = cov_world_to_gtsam(T_kf[:3, :3], self.kfs.online_cov(k))
        shift = shift_cov = None
        if plan is not None:  # the source's offset as predicted for this fix
            G = plan.G[:len(fix.measured)]
            shift, shift_cov = G @ plan.mean, G @ plan.cov @ G.T
        inn = innovation_d2(fix, T_kf, cov_kf, T_rel, cov_res, shift, shift_cov)
        applied = fix  # without its height when that is refused; the outcome names the fix as given
        if inn.height_d2 is not None and not inn.height_d2 <= cfg.height_gate_chi2:
            log.info("fix at t=%.2f: its height refused (d2 %.1f > %.1f); planar part gated", fix.t_meas,
                     inn.height_d2, cfg.height_gate_chi2)
            applied = fix.planar()
            factor, cov_res = place(applied)
        d2, dist = inn.d2, inn.distance_m
        if dist > cfg.gate_distance_m:
            return FixOutcome(fix, False, f"distance gate {dist:.1f} m > {cfg.gate_distance_m:.1f} m", d2)
        if d2 > cfg.gate_chi2:
            return FixOutcome(fix, False, f"Mahalanobis gate d2 {d2:.1f} > {cfg.gate_chi2:.1f}", d2)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(factor)
        values, stamps = gtsam.Values(), {}
        if plan is not None:  # the offset's prior or Gauss-Markov step, before the fix's factor
            offset_graph = gtsam.NonlinearFactorGraph(plan.graph)
            offset_graph.push_back(graph)
            graph, values = offset_graph, plan.values
            if plan.new and self.solver.fixed_lag:
                stamps[plan.key] = self._stamp(self.kfs.t[-1])
        idx, failure = self._fix_update(graph, values, stamps)
        if idx is None:
            return FixOutcome(fix, False, failure, d2)
        rec = FixRecord(applied, k, X(k), T_rel, cov_res, idx[-1])
        if plan is not None:
            self._stamps.update(stamps)
            rec.offset_key, rec.offset_rows = plan.key, plan.G[:len(applied.measured)]
        self.n_heights_refused += applied is not fix
        self.fixes.append(rec)
        self._retract_outliers()
        # fixed-lag with an offset: the newest keyframe keeps its covariance from before the fix (an
        # upper bound) until the next keyframe. GTSAM's fixed-lag smoother orders the update without
        # the newest keyframe last, and with the offset chain its marginal after a fix cost a median
        # of 35 ms, p99 225 ms (the demo's 250 m), against 0.8 / 2.4 ms after a keyframe
        self._refresh_latest(self.cov_kf if plan is not None and self.solver.fixed_lag else None)
        if plan is not None:  # the offset is the source's latest (retracted or not), where the estimate now is
            self.offsets.commit(plan, fix, (self.T_kf @ self._motion_since_kf())[:2, 3])
        if not rec.active:
            return FixOutcome(fix, False, rec.retracted_reason, d2)
        return FixOutcome(fix, True, "", d2)

    def _fix_update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values | None = None,
                    stamps: dict[int, float] | None = None) -> tuple[list[int] | None, str]:
        """``graph`` (a fix's or anchors' factors, and the new ``values`` they bring with their
        fixed-lag ``stamps``: a source offset) in one update with the newest keyframe last, and
        ``extra_iterations``: the new factors' indices, or None and the reason when the solver
        failed (its state then restored)."""
        snap = self.solver.snapshot() if self.config.snapshot_before_fixes else None
        alive = set(self.solver._alive)
        try:
            idx = self._timed_update(graph, values if values is not None else gtsam.Values(), stamps,
                                     keep_latest_root=True)
            self.solver.extra_iterations(self.config.fixes.extra_iterations, self._latest_keys())
        except (SolverUpdateError, RuntimeError, ValueError) as exc:
            self.solver.restore(snap, alive)
            self.n_failed_updates += 1
            return None, f"solver update failed: {exc}"
        return idx, ""

    def _retract_outliers(self) -> None:
        """Remove, worst first (by residual over bound), fixes whose residual stays above
        ``retract_chi2`` (``retract_chi2_with_height`` with a height) after optimisation."""
        cfg = self.config.fixes
        for _ in range(3):
            live = [r for r in self.fixes if r.active and self.solver.alive(r.key)]
            if not live:
                return
            offsets = [self.solver.estimate(r.offset_key) if r.offset_key is not None and self.solver.alive(r.offset_key)
                       else None for r in live]
            d2 = residual_d2_many(live, np.array([self.solver.pose(r.key) for r in live]), offsets)
            # each fix against the bound of its own dof (a height adds one)
            bound = np.array([cfg.retract_chi2 if r.fix.height is None else cfg.retract_chi2_with_height for r in live])
            worst = int(np.argmax(d2 / bound))
            if d2[worst] <= bound[worst]:
                return
            rec = live[worst]
            try:
                self._timed_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), remove=[rec.factor_index], keep_latest_root=True)
                self.solver.extra_iterations(cfg.extra_iterations, self._latest_keys())
            except (SolverUpdateError, RuntimeError, ValueError) as exc:
                log.warning("could not retract fix at t=%.2f: %s", rec.fix.t_meas, exc)
                return
            rec.active = False
            rec.retracted_reason = f"retracted: residual d2 {d2[worst]:.1f} > {bound[worst]:.1f} after optimisation"
            log.info("fix at t=%.2f %s", rec.fix.t_meas, rec.retracted_reason)

    def _remap_fix_factors(self, index_map: dict[int, int]) -> None:
        """The solver was rebuilt: its factors have new indices (``Solver.on_rebuild``); a fix
        whose factor is gone (marginalized with its keyframe) gets -1, not an index that now
        belongs to another factor."""
        for r in self.fixes:
            if r.active:
                r.factor_index = index_map.get(r.factor_index, -1)


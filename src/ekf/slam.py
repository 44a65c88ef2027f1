"""EKF-SLAM of the reference design, implementing :class:`reloc.backend.Backend`.

Reads like the paper (II.C): predict from command speed + IMU orientation increments with
dynamic process noise; update landmarks from stereo observations, each through its kind's
update (:mod:`ekf.kinds`; rocks: :mod:`ekf.rocks`, association and the stereo point model in
:mod:`reloc`); apply planar global fixes behind a distance/yaw gate and a Mahalanobis gate; roll
back and replay for late fixes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ekf.blas import blas_limit
from ekf.config import EkfConfig
from ekf.errors import EkfError, EkfInputError
from ekf.history import Entry, History
from ekf.kinds import kind_counts, kind_updates, resolved_ekf_config
from ekf.motion import propagate, split_step
from ekf.state import CALIB_DIM, POSE_DIM, FilterState
from ekf.updates import attitude_model, fix_model, fix_residual, joseph_update
from reloc.backend import (
    PLANAR_POSE_INDICES,
    Backend,
    BackendStats,
    FixOutcome,
    LandmarkMap,
    LandmarkUpdateReport,
    PoseEstimate,
    Trajectory,
    offset_report,
)
from reloc.calibration import calibration_report
from reloc.covariance import distance_correlation_scale
from reloc.geometry import log_so3, project_so3, wrap_angle
from reloc.landmark_book import LandmarkBook
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep, uphill_rad
from reloc.rows import RowBuffer

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _FixBias:
    """A fix's update with its source's shared error as a state (``EkfSlam._fix_bias_model``):
    columns (pose and offset), Jacobian, white noise, the propagated offset's share of ``h``, the
    propagated (pose, offset) covariance, and the propagation to apply once the fix is taken."""

    cols: np.ndarray
    H: np.ndarray
    R: np.ndarray
    offset: np.ndarray
    P_sub: np.ndarray
    source: str
    fcols: np.ndarray
    rho: float
    Q: np.ndarray

    def propagate(self, s: FilterState) -> None:
        """``f <- rho f`` and ``P_ff += Q`` on the whole state (rows and columns of ``f``)."""
        s.fix_bias[self.source] = self.rho * s.fix_bias[self.source]
        f = self.fcols
        s.P[f, :] *= self.rho
        s.P[:, f] *= self.rho
        s.P[np.ix_(f, f)] += self.Q

_ORTHONORMALISE_EVERY = 200
_T_EPS = 1e-9
_I3 = np.eye(3)


class EkfSlam(Backend):
    """EKF-SLAM back-end: ``EkfSlam(initial, config)``; see :class:`reloc.backend.Backend`."""

    name = "ekf"

    def __init__(self, initial: PoseEstimate, config: EkfConfig | None = None) -> None:
        self.config = config or EkfConfig()
        T = np.asarray(initial.T_world_base, dtype=float)
        cov = np.asarray(initial.cov, dtype=float)
        if T.shape != (4, 4) or cov.shape != (6, 6) or not (np.all(np.isfinite(T)) and np.all(np.isfinite(cov))):
            raise EkfInputError("initial pose must have a finite (4, 4) T_world_base and (6, 6) cov")
        if not math.isfinite(initial.t):
            raise EkfInputError(f"initial pose time is not finite: {initial.t}")
        P0 = 0.5 * (cov + cov.T)
        cal = self.config.calibration
        head = POSE_DIM
        if cal.enabled:  # stereo rotation error and range scale, with their priors
            head = POSE_DIM + CALIB_DIM
            prior = cal.prior_sigmas() ** 2  # a zero sigma keeps that term nominal
            P0 = np.block([[P0, np.zeros((POSE_DIM, CALIB_DIM))], [np.zeros((CALIB_DIM, POSE_DIM)), np.diag(prior)]])
        n_calib = head - POSE_DIM
        cfg = self.config

        def scalar_state(on: bool, sigma: float) -> int:
            """Append a scalar state with prior ``sigma`` to the head when ``on``: its column, or -1."""
            nonlocal P0, head
            if not on:
                return -1
            col, head = head, head + 1
            P0 = np.block([[P0, np.zeros((col, 1))], [np.zeros((1, col)), np.array([[sigma ** 2]])]])
            return col

        # after the calibration: the IMU heading's drift rate, then the wheels' slip bias, its
        # growth with the slope and its wander with the soil
        bias_col = scalar_state(cfg.yaw_rate_bias_sigma_radps > 0, cfg.yaw_rate_bias_sigma_radps)
        slip_col = scalar_state(cfg.slip_sigma > 0, cfg.slip_sigma)
        slope_col = scalar_state(slip_col >= 0 and cfg.slope_slip_sigma_per_rad > 0, cfg.slope_slip_sigma_per_rad)
        gm_col = scalar_state(slip_col >= 0 and cfg.slip_gm_sigma > 0, cfg.slip_gm_sigma)
        # the fixes' shared error per source (FixGateConfig): zero until its first fix, which
        # replaces its covariance (rho = 0 there); until then a unit variance, uncorrelated, keeps
        # the covariance positive definite
        fix_bias_cols = {}
        if cfg.fix_gate.correlation_model == "bias":
            for src in dict.fromkeys(cfg.fix_gate.bias_sources):
                xyyaw_cols = [scalar_state(True, 1.0) for _ in range(3)]
                fix_bias_cols[src] = xyyaw_cols[0]
        self._s = FilterState(
            t=float(initial.t),
            t_input=float(initial.t),
            p_world=T[:3, 3].copy(),
            R_world_base=project_so3(T[:3, :3]),
            l_world=np.zeros((0, 3)),
            P=P0,
            head=head,
            n_calib=n_calib,
            bias_col=bias_col,
            slip_col=slip_col,
            slope_col=slope_col,
            gm_col=gm_col,
            fix_bias_cols=fix_bias_cols,
            fix_bias={src: np.zeros(3) for src in fix_bias_cols},
            book=LandmarkBook(self.config.book),
            t_last_attitude=float(initial.t),
            t_last_checkpoint=float(initial.t),
        )
        if self.config.first_estimate_jacobians:
            self._s.p_lin = self._s.p_world.copy()
            self._s.l_lin = np.zeros((0, 3))
        self._kinds = kind_updates(self.config)
        self._hist = History(self.config.history_s)
        self._traj = RowBuffer(1 + 16 + POSE_DIM * POSE_DIM)  # t, T_world_base, pose covariance
        self._replaying = False
        self._count = {"n_predict": 0, "n_landmark_frames": 0, "n_fixes_accepted": 0, "n_fixes_rejected": 0,
                       "n_late_fixes": 0, "n_replayed_entries": 0, "n_attitude_updates": 0}
        self._reject_reasons: dict[str, int] = {}
        self._count["n_consensus_resets"] = 0
        self._count["n_heights_refused"] = 0  # fixes applied without their height (FixGateConfig.height_chi2)
        # fixes applied as catalog entries on their landmarks (FixGateConfig.anchors), the landmarks
        # anchored, and anchors whose landmark a replay no longer had
        self._count.update(n_anchor_fixes=0, n_anchors=0, n_anchors_lost_in_replay=0)
        self._applied: GlobalFix | None = None  # the last fix as _gate_and_apply applied it
        self._count["n_first_estimate_resets"] = 0  # pose corrections beyond first_estimate_tol_m
        self._gate_rejects: list[tuple[float, np.ndarray]] = []  # (t_meas, innovation) of Mahalanobis rejections
        self._consensus_opened: dict[tuple, np.ndarray] = {}  # x, y, yaw variances a consensus fix opened (for replays)
        self._record()
        self._hist.checkpoint(self._s, len(self._traj))

    # ------------------------------------------------------------------ protocol
    def predict(self, step: OdometryStep) -> None:
        """Propagate the pose (and its cross covariances) over one odometry step."""
        self._check_step(step)
        self._count["n_predict"] += 1
        self._do_step(step)

    def observe(self, obs) -> LandmarkUpdateReport:
        """Associate, update and initialise landmarks from one frame of a registered kind, through
        that kind's update (:mod:`ekf.kinds`); hygiene and the map bound."""
        self._kinds.for_obs(obs).check(obs)
        if obs.t < self._s.t_input:
            raise EkfInputError(
                f"{type(obs).__name__} at t={obs.t:.6f} s is out of order: newest input is {self._s.t_input:.6f} s")
        self._count["n_landmark_frames"] += 1
        with blas_limit(self.config.blas_threads):
            return self._do_obs(obs)

    def expect_fix(self, t_meas: float) -> None:
        """A fix for ``t_meas`` (at or after the state's time) may arrive later: keep a rollback
        point here, so that its replay starts at ``t_meas`` rather than at the last periodic
        checkpoint. Results do not change (a replay from any earlier checkpoint reproduces this
        state); only the replayed stretch gets shorter. The periodic schedule is untouched."""
        s = self._s
        if not t_meas >= s.t - _T_EPS:
            return
        cps = self._hist.checkpoints
        if cps and cps[-1].t >= s.t - _T_EPS and cps[-1].log_index == len(self._hist.log):
            return
        self._hist.checkpoint(s, len(self._traj))

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        """Gate and apply a planar fix at ``fix.t_meas``, rolling back and replaying when it is late."""
        with blas_limit(self.config.blas_threads):
            return self._apply_fix(fix)

    def _apply_fix(self, fix: GlobalFix) -> FixOutcome:
        s = self._s
        if fix.t_meas > s.t + self.config.future_tolerance_s:
            return self._rejected(fix, f"ahead of the filter (t_meas {fix.t_meas:.3f} s > state {s.t:.3f} s)")
        if fix.anchors and self.config.fix_gate.anchors:
            outcome = self._apply_anchors(fix)
            if outcome is not None:  # the entries on the landmarks; the height (if any) on the pose
                if outcome.accepted and fix.height is not None:
                    self._apply_pose_fix(fix.height_only())
                return self._counted(outcome)
        return self._counted(self._apply_pose_fix(fix))

    def _apply_pose_fix(self, fix: GlobalFix) -> FixOutcome:
        """The fix on the pose at its ``t_meas`` (rolled back to when late), not counted."""
        s = self._s
        if fix.t_meas >= s.t_input:
            outcome = self._gate_and_apply(fix)
            if outcome.accepted:
                self._hist.log.append(Entry("fix", fix.t_meas, self._applied))
            return outcome
        if fix.t_meas < s.t_input - self.config.history_s or fix.t_meas < self._hist.t_start:
            return FixOutcome(
                fix, False, f"older than history (t_meas {fix.t_meas:.3f} s, history starts at "
                f"{max(self._hist.t_start, s.t_input - self.config.history_s):.3f} s)")
        return self._apply_late(fix)

    def _anchor_rows(self, fix: GlobalFix) -> np.ndarray | None:
        """The state rows of the landmarks ``fix``'s anchors name, or None when one is not a
        confirmed landmark of the state (of its kind)."""
        book, rows = self._s.book, []
        for a in fix.anchors:
            upd = self._kinds.named(a.kind)
            if upd is None:
                return None
            hit = np.flatnonzero((book.ids == a.landmark_id) & (book.kind == upd.code) & book.confirmed)
            if hit.size != 1:
                return None
            rows.append(int(hit[0]))
        return np.array(rows, dtype=int)

    def _apply_anchors(self, fix: GlobalFix, force: bool = False) -> FixOutcome | None:
        """Put ``fix``'s catalog entries on its landmarks (``FixGateConfig.anchors``): the update
        ``z = l_xy + v``, ``v`` the entry's error, on the landmarks' (x, y) now (a landmark does not
        move, so no rollback), gated on its squared Mahalanobis distance (``anchor_chi2_per_dof``
        times 2 per landmark) and on the distance gate per landmark. None when a landmark has left
        the state (the fix is then taken as a pose); ``force``: a replay, no gate."""
        s, gate = self._s, self.config.fix_gate
        rows = self._anchor_rows(fix)
        if rows is None:
            return None
        if not force and np.any(s.book.catalog_row[rows] >= 0):
            return FixOutcome(fix, False, "anchored already: a landmark holds a catalog entry")
        cols = s.landmark_cols(rows).reshape(-1, 3)[:, :2].ravel()
        nu = np.concatenate([a.xy_m - s.l_world[r, :2] for a, r in zip(fix.anchors, rows)])
        R = np.zeros((len(cols), len(cols)))
        for k, a in enumerate(fix.anchors):
            R[2 * k:2 * k + 2, 2 * k:2 * k + 2] = a.cov_xy
        if not force:
            S = s.P[np.ix_(cols, cols)] + R
            for k in range(len(rows)):  # each landmark against its own innovation's spread
                dist = math.hypot(nu[2 * k], nu[2 * k + 1])
                limit = gate.distance_limit_m(S[2 * k:2 * k + 2, 2 * k:2 * k + 2])
                if dist > limit:
                    return FixOutcome(fix, False, f"distance gate (anchor) {dist:.2f} m > {limit:.2f} m")
            d2 = float(nu @ np.linalg.solve(S, nu))
            if not d2 <= gate.anchor_chi2_per_dof * len(cols):
                return FixOutcome(fix, False, f"Mahalanobis gate (anchor) d2 {d2:.1f} > "
                                  f"{gate.anchor_chi2_per_dof * len(cols):.2f}", d2)
        s.P, res = joseph_update(s.P, cols, np.eye(len(cols)), nu, R)
        s.inject(res.dx)
        s.book.catalog_row[rows] = [a.catalog_row for a in fix.anchors]
        self._record()
        self._hist.log.append(Entry("anchor", s.t, fix))
        if not self._replaying:
            self._count["n_anchor_fixes"] += 1
            self._count["n_anchors"] += len(rows)
        return FixOutcome(fix, True, "", res.d2)

    def estimate(self) -> PoseEstimate:
        """Current pose of base_link in world with its (6, 6) covariance over ``[dp, dtheta]``."""
        s = self._s
        return PoseEstimate(t=s.t, T_world_base=self._T(), cov=s.P[:POSE_DIM, :POSE_DIM].copy())

    def landmark_map(self, kind: str) -> LandmarkMap:
        """Confirmed landmarks of ``kind`` in world with marginal covariances (tentative ones are
        left out); empty for a kind not observed yet."""
        upd = self._kinds.named(kind)
        return LandmarkMap.empty(kind) if upd is None else upd.landmark_map(self._s)

    def trajectory(self) -> Trajectory:
        """Filtered pose history (one entry per step, or per ``trajectory_period_s``)."""
        rows = self._traj.array()
        return Trajectory(
            t=rows[:, 0].copy(),
            T_world_base=rows[:, 1:17].reshape(-1, 4, 4).copy(),
            cov=rows[:, 17:].reshape(-1, POSE_DIM, POSE_DIM).copy(),
        )

    def stats(self) -> BackendStats:
        """Counters, with landmark, association and fix-rejection details in ``extra``."""
        c = self._count
        extra = {k: v for k, v in c.items() if k not in ("n_predict", "n_landmark_frames", "n_fixes_accepted", "n_fixes_rejected")}
        extra.update(kind_counts(self._kinds))
        extra["n_tentative"] = int(np.sum(~self._s.book.confirmed))
        extra["fix_reject_reasons"] = dict(self._reject_reasons)
        if self._s.calibrated:
            extra["calibration"] = self.calibration()
        if self._s.has_yaw_bias:
            b = self._s.bias_col
            extra["yaw_rate_bias_deg_per_h"] = {"estimate": round(math.degrees(self._s.yaw_bias) * 3600, 4),
                                                "sigma": round(math.degrees(math.sqrt(self._s.P[b, b])) * 3600, 4)}
        if self._s.has_slip:
            g = self._s.slip_col
            extra["slip"] = {"estimate": round(self._s.slip, 5), "sigma": round(math.sqrt(self._s.P[g, g]), 5)}
        if self._s.has_slope_slip:
            k = self._s.slope_col
            extra["slope_slip_per_rad"] = {"estimate": round(self._s.slope_gain, 5),
                                           "sigma": round(math.sqrt(self._s.P[k, k]), 5)}
        if self._s.has_slip_gm:
            k = self._s.gm_col
            extra["slip_gm"] = {"estimate": round(self._s.slip_gm, 5), "sigma": round(math.sqrt(self._s.P[k, k]), 5)}
        offsets = {}  # the fixes' shared errors (correlation_model "bias"), of the sources that sent a fix
        for src, col in self._s.fix_bias_cols.items():
            if src in self._s.fix_last_rows:
                offsets[src] = offset_report(self._s.fix_bias[src], np.sqrt(np.diagonal(self._s.P)[col:col + 3]))
        if offsets:
            extra["fix_offset"] = offsets
        return BackendStats(
            n_predict=c["n_predict"], n_landmark_frames=c["n_landmark_frames"],
            n_fixes_accepted=c["n_fixes_accepted"], n_fixes_rejected=c["n_fixes_rejected"],
            n_landmarks=int(np.sum(self._s.book.confirmed)), extra=extra,
        )

    @classmethod
    def resolved_config(cls, config: EkfConfig) -> dict:
        """The resolved config, with every registered kind's resolved EKF settings in ``kinds``."""
        return resolved_ekf_config(config)

    def calibration(self) -> dict:
        """The estimated stereo calibration (empty without calibration states): rotation vector
        of ``E`` (deg, base_link), range scale, and their sigmas."""
        s = self._s
        if not s.calibrated:
            return {}
        sig = np.sqrt(np.diag(s.P)[POSE_DIM:POSE_DIM + CALIB_DIM])
        return calibration_report(log_so3(s.calib_R), s.calib_s, sig[:3], sig[3])

    @property
    def state_vector_size(self) -> int:
        """Dimension of the error state (6 [+ 4 calibration] [+ 1 yaw-rate bias] [+ 1 slip [+ 1 slope gain] [+ 1 slip wander]] + 3 x landmarks, tentative included)."""
        return int(self._s.P.shape[0])

    def full_covariance(self) -> np.ndarray:
        """A copy of the joint covariance (6 + 3n, 6 + 3n)."""
        return self._s.P.copy()

    # ------------------------------------------------------------------ validation
    def _check_step(self, step: OdometryStep) -> None:
        try:
            vals = np.array([step.t0, step.t1, step.v_mps, step.extra_forward_var_m2, step.extra_yaw_var_rad2],
                            dtype=float)
            R0 = np.asarray(step.R_ref_base0, dtype=float)
            R1 = np.asarray(step.R_ref_base1, dtype=float)
        except (TypeError, ValueError, AttributeError) as exc:
            raise EkfInputError(f"OdometryStep is malformed: {exc}") from exc
        if R0.shape != (3, 3) or R1.shape != (3, 3):
            raise EkfInputError(f"OdometryStep rotations must be (3, 3), got {R0.shape} and {R1.shape}")
        if not np.isfinite(np.concatenate([vals, R0.ravel(), R1.ravel()])).all():
            raise EkfInputError(f"OdometryStep at t1={step.t1} contains NaN or inf")
        for name, R in (("R_ref_base0", R0), ("R_ref_base1", R1)):
            if np.abs(R.T @ R - _I3).max() > 1e-6:
                raise EkfInputError(f"OdometryStep.{name} at t1={step.t1} is not a rotation matrix")
        for name in ("extra_forward_var_m2", "extra_yaw_var_rad2"):
            if getattr(step, name) < 0:
                raise EkfInputError(f"OdometryStep.{name} at t1={step.t1} is negative ({getattr(step, name)})")
        if step.t1 <= step.t0:
            raise EkfInputError(f"OdometryStep t1 ({step.t1}) must be after t0 ({step.t0})")
        if step.t0 < self._s.t - _T_EPS or step.t1 <= self._s.t_input:
            raise EkfInputError(
                f"OdometryStep [{step.t0:.6f}, {step.t1:.6f}] s is out of order: the filter is at "
                f"{self._s.t:.6f} s (newest input {self._s.t_input:.6f} s)")

    # ------------------------------------------------------------------ processing (also used by replay)
    def _do_step(self, step: OdometryStep) -> None:
        s, cfg = self._s, self.config
        if s.refresh_first_estimates(cfg.first_estimate_tol_m) and not self._replaying:
            self._count["n_first_estimate_resets"] += 1
        p0 = s.p_world
        uphill = uphill_rad(step) if s.has_slope_slip else 0.0  # the slope under this step
        p1, R1, F, Q = propagate(s.p_world, s.R_world_base, step, cfg.motion, s.p_lin, s.yaw_bias, s.slip_at(uphill))
        P = s.P
        Ppp = F @ P[:POSE_DIM, :POSE_DIM] @ F.T + Q
        if P.shape[0] > POSE_DIM:  # landmarks, or the calibration, yaw-rate bias and slip states
            # only the pose rows of the cross terms change: O(n)
            P[:3, POSE_DIM:] += F[:3, 3:] @ P[3:6, POSE_DIM:]
            P[POSE_DIM:, :3] = P[:3, POSE_DIM:].T
        P[:POSE_DIM, :POSE_DIM] = 0.5 * (Ppp + Ppp.T)
        if s.has_yaw_bias:
            s.yaw_bias_step(step.dt, cfg.yaw_rate_bias_walk_radps_rsqrt_s ** 2 * step.dt)
        if s.has_slip:
            a = math.exp(-step.dt / cfg.slip_gm_tau_s) if s.has_slip_gm else 1.0
            s.slip_step(p1 - p0, cfg.slip_walk_rsqrt_s ** 2 * step.dt, uphill,
                        cfg.slope_slip_walk_rsqrt_s ** 2 * step.dt, a, cfg.slip_gm_sigma ** 2 * (1.0 - a * a))
        s.p_world, s.R_world_base, s.t = p1, R1, step.t1
        if s.first_estimates:
            s.p_lin = p1.copy()
        s.t_input = max(s.t_input, step.t1)
        s.n_steps_since_orthonormalise += 1
        if s.n_steps_since_orthonormalise >= _ORTHONORMALISE_EVERY:
            s.orthonormalise()
        if cfg.attitude_period_s > 0 and s.t - s.t_last_attitude >= cfg.attitude_period_s - _T_EPS:
            with blas_limit(cfg.blas_threads):
                self._attitude_update(step.R_ref_base1)
        self._record()
        self._hist.log.append(Entry("step", step.t1, step))
        if s.t - s.t_last_checkpoint >= cfg.checkpoint_period_s - _T_EPS:
            s.t_last_checkpoint = s.t
            self._hist.checkpoint(s, len(self._traj))
            self._hist.prune(s.t_input)

    def _attitude_update(self, R_ref_base: np.ndarray) -> None:
        s = self._s
        nu, H = attitude_model(s.R_world_base, R_ref_base)
        R_meas = np.eye(2) * self.config.attitude_sigma_rad**2
        s.P, res = joseph_update(s.P, np.arange(POSE_DIM), H, nu, R_meas)
        s.inject(res.dx)
        s.t_last_attitude = s.t
        if not self._replaying:
            self._count["n_attitude_updates"] += 1

    def _do_obs(self, obs) -> LandmarkUpdateReport:
        s = self._s
        s.t_input = max(s.t_input, obs.t)
        report = self._kinds.for_obs(obs).update(s, obs, count=not self._replaying)
        self._record()
        self._hist.log.append(Entry("obs", obs.t, obs))
        return report

    def _gate_and_apply(self, fix: GlobalFix, force: bool = False) -> FixOutcome:
        """Gate ``fix`` (not when ``force``: a replay of an applied one) and apply it; the fix as
        applied (without its height when that was refused) is left in ``self._applied``."""
        s, gate = self._s, self.config.fix_gate
        applied = fix
        h, H = fix_model(s.p_world, s.R_world_base, height=fix.height is not None)
        if fix.height is not None and not force:
            nu_z = fix.height.z_m - h[3]
            S_z = float(H[3] @ s.P[:POSE_DIM, :POSE_DIM] @ H[3]) + fix.height.var_m2
            if not nu_z * nu_z / S_z <= gate.height_chi2:
                log.info("t_meas=%.1f s: the fix's height refused (innovation %.2f m, d2 %.1f > %.2f); planar part gated",
                         fix.t_meas, nu_z, nu_z * nu_z / S_z, gate.height_chi2)
                applied, h, H = fix.planar(), h[:3], H[:3]
        self._applied = applied
        nu = fix_residual(applied.measured, h)
        cols, bias = np.arange(POSE_DIM), None
        if applied.source in s.fix_bias_cols:  # the shared error a state (correlation_model "bias")
            bias = self._fix_bias_model(applied, H)
            cols, H, R_fix = bias.cols, bias.H, bias.R
            nu -= bias.offset
            nu[2] = wrap_angle(float(nu[2]))
        else:
            R_fix = self._fix_cov(applied)
        P_sub = s.P[np.ix_(cols, cols)] if bias is None else bias.P_sub
        S = H[:3] @ P_sub @ H[:3].T + R_fix[:3, :3]
        if not force:  # a replay of an applied fix is not gated again
            dist, limit = math.hypot(nu[0], nu[1]), gate.distance_limit_m(S[:2, :2])
            if dist > limit:
                return FixOutcome(fix, False, f"distance gate {dist:.2f} m > {limit:.2f} m")
            if abs(math.degrees(nu[2])) > gate.yaw_deg:
                return FixOutcome(fix, False, f"yaw gate {abs(math.degrees(nu[2])):.1f} deg > {gate.yaw_deg:.1f} deg")
        d2 = float(nu[:3] @ np.linalg.solve(S, nu[:3]))  # the planar part: the height was gated above
        key = (fix.t_meas, fix.t_recv, fix.x_m, fix.y_m, fix.yaw_rad)
        opened = None  # the consensus inflation (x, y, yaw variances) applied with this fix
        if force and key in self._consensus_opened:  # a replayed consensus fix: the same inflation again
            opened = self._consensus_opened[key]
        elif not force and not d2 <= gate.chi2:
            if not self._consensus(fix.t_meas, nu[:3]):
                return FixOutcome(fix, False, f"Mahalanobis gate d2 {d2:.1f} > {gate.chi2:.2f}", d2)
            # the rejected fixes agree with each other: open the covariance by the innovation
            log.info("t_meas=%.1f s: %d consistent fixes rejected, covariance (%s) inflated by the innovation "
                     "(%.2f m, %.1f deg)", fix.t_meas, gate.consensus_n, self._opens(bias), math.hypot(nu[0], nu[1]),
                     math.degrees(nu[2]))
            opened = nu[:3] ** 2
            self._consensus_opened[key] = opened
            self._gate_rejects.clear()
            self._count["n_consensus_resets"] += 1
        if bias is not None:
            bias.propagate(s)
        if opened is not None:
            self._open(opened, bias)
        s.fix_last_xy = {**s.fix_last_xy, fix.source: (float(s.p_world[0]), float(s.p_world[1]))}  # where, by the estimate
        s.fix_last_rows = {**s.fix_last_rows, fix.source: fix.catalog_rows}
        s.P, res = joseph_update(s.P, cols, H, nu, R_fix)
        s.inject(res.dx)
        horizon = s.t - max(gate.correlation_s, 0.0) - self.config.history_s
        s.fix_times = tuple(t for t in s.fix_times if t >= horizon) + (fix.t_meas,)
        self._record()
        if applied is not fix:
            self._count["n_heights_refused"] += 1
        return FixOutcome(fix, True, "", d2)

    def _fix_bias_model(self, fix: GlobalFix, H_pose: np.ndarray) -> _FixBias:
        """The update of ``fix`` with its source's shared error as a state (``correlation_model``
        "bias", see :class:`FixGateConfig`): ``z = h(x) + f + v``, ``f`` first-order Gauss-Markov
        along the distance between the source's fixes, propagated to this fix (not yet in ``P``:
        a rejected fix leaves the state as it was)."""
        s, gate = self._s, self.config.fix_gate
        c = s.fix_bias_cols[fix.source]
        fcols = np.arange(c, c + 3)
        rho = math.exp(-self._distance_since_last_fix(fix.source) / gate.correlation_length_m)
        rows, last_rows = set(fix.catalog_rows), s.fix_last_rows.get(fix.source, ())
        if rows and last_rows:  # the share of this fix's catalog entries that the last one used too
            rho *= len(rows.intersection(last_rows)) / len(rows)
        match, _ = fix.split_cov()
        Q = (1.0 - rho * rho) * gate.bias_share * match
        R = fix.unshared(gate.bias_share).cov  # the white rest, a height's terms propagated again
        H = np.zeros((len(fix.measured), POSE_DIM + 3))
        H[:, :POSE_DIM] = H_pose
        H[:3, POSE_DIM:] = np.eye(3)
        if fix.height is not None:  # z read at the fix's (x, y): the offset moves it along the gradient g
            H[3, POSE_DIM:] = fix.height_model()[0]
        cols = np.concatenate([np.arange(POSE_DIM), fcols])
        P_sub = s.P[np.ix_(cols, cols)].copy()
        P_sub[POSE_DIM:, :] *= rho
        P_sub[:, POSE_DIM:] *= rho
        P_sub[POSE_DIM:, POSE_DIM:] += Q
        offset = H[:, POSE_DIM:] @ (rho * s.fix_bias[fix.source])  # what the propagated offset adds to h
        return _FixBias(cols, H, R, offset, P_sub, fix.source, fcols, rho, Q)

    def _distance_since_last_fix(self, source: str) -> float:
        """Planar distance (m) between the estimate now and where it was at the last fix applied
        from ``source`` (inf before the first)."""
        s = self._s
        last = s.fix_last_xy.get(source)
        return math.inf if last is None else math.hypot(s.p_world[0] - last[0], s.p_world[1] - last[1])

    def _fix_cov(self, fix: GlobalFix) -> np.ndarray:
        """The covariance ``fix`` is applied with: its own, or (``fix_gate.correlation_model``
        "distance") its match covariance re-scaled for its correlation with the last fix applied
        from the same source (the distance between the estimate's positions at the two fixes),
        times the recent-fix factor when ``fix_gate.correlation_s`` is on."""
        s, gate = self._s, self.config.fix_gate
        if gate.correlation_model == "distance":
            d = self._distance_since_last_fix(fix.source)
            fix = fix.recorrelated(distance_correlation_scale(d, gate.correlation_length_m))
        if gate.correlation_s <= 0:
            return fix.cov
        n_recent = sum(1 for t in s.fix_times if fix.t_meas - gate.correlation_s <= t <= fix.t_meas)
        return fix.cov * (1.0 + n_recent)

    def _opens(self, bias: _FixBias | None) -> str:
        """What a consensus opens: the pose, or with the fix's source offset a state
        (``correlation_model`` "bias") ``fix_gate.consensus_opens``."""
        return "pose" if bias is None else self.config.fix_gate.consensus_opens

    def _open(self, var_xyyaw: np.ndarray, bias: _FixBias | None) -> None:
        """Add the consensus inflation ``var_xyyaw`` (3,) to the pose's x, y, yaw variances and/or
        to the fix source's offset (:meth:`_opens`)."""
        s, what = self._s, self._opens(bias)
        if what in ("pose", "pose_and_offset"):
            i = np.array(PLANAR_POSE_INDICES)
            s.P[i, i] += var_xyyaw
        if what in ("offset", "pose_and_offset"):
            s.P[bias.fcols, bias.fcols] += var_xyyaw

    def _consensus(self, t_meas: float, nu: np.ndarray) -> bool:
        """Record a Mahalanobis rejection; True when it completes a consistent set (see FixGateConfig)."""
        gate = self.config.fix_gate
        if gate.consensus_n <= 0:
            return False
        self._gate_rejects = [(t, v) for t, v in self._gate_rejects if t >= t_meas - gate.consensus_window_s]
        self._gate_rejects.append((t_meas, nu.copy()))
        if len(self._gate_rejects) < gate.consensus_n:
            return False
        V = np.array([v for _, v in self._gate_rejects[-gate.consensus_n:]])
        spread_xy = np.linalg.norm(V[:, :2] - V[:, :2].mean(axis=0), axis=1).max()
        spread_yaw = np.abs(V[:, 2] - V[:, 2].mean()).max()
        return bool(spread_xy <= gate.consensus_tol_m and math.degrees(spread_yaw) <= gate.consensus_tol_deg)

    def _apply_late(self, fix: GlobalFix) -> FixOutcome:
        """Roll back to the newest checkpoint at or before t_meas, replay to t_meas (splitting the
        step that straddles it), apply the fix, replay the rest; on rejection restore everything."""
        i = self._hist.latest_before(fix.t_meas)
        ckpt = self._hist.checkpoints[i]
        saved = (self._s, self._hist.snapshot(), self._traj.array(ckpt.n_trajectory))  # the trajectory's tail only
        tail = self._hist.rewind(i)
        self._s = ckpt.state.copy()
        self._traj.truncate(ckpt.n_trajectory)
        k = next((j for j, e in enumerate(tail) if e.t > fix.t_meas), len(tail))
        before, after = tail[:k], tail[k:]
        if after and after[0].kind == "step" and after[0].item.t0 < fix.t_meas:
            a, b = split_step(after[0].item, fix.t_meas)
            before = before + [Entry("step", a.t1, a)]
            after = [Entry("step", b.t1, b)] + after[1:]
        self._replaying = True
        try:
            self._replay(before)
            outcome = self._gate_and_apply(fix)
            if not outcome.accepted:
                self._s, snap = saved[0], saved[1]
                self._hist.restore(snap)
                self._traj.truncate(ckpt.n_trajectory)
                self._traj.extend(saved[2])
                return outcome
            self._hist.log.append(Entry("fix", fix.t_meas, self._applied))
            self._replay(after)
        finally:
            self._replaying = False
        self._count["n_late_fixes"] += 1
        self._count["n_replayed_entries"] += len(tail)
        return outcome

    def _replay(self, entries: list[Entry]) -> None:
        for e in entries:
            if e.kind == "step":
                self._do_step(e.item)
            elif e.kind == "obs":  # a landmark frame of any kind: its kind's update again
                self._do_obs(e.item)
            elif e.kind == "fix":
                self._gate_and_apply(e.item, force=True)
                self._hist.log.append(e)
            elif e.kind == "anchor":  # its landmarks may be gone in the replay: then nothing to anchor
                if self._apply_anchors(e.item, force=True) is None:
                    self._count["n_anchors_lost_in_replay"] += 1
            else:
                raise EkfError(f"history entry of unknown kind {e.kind!r} at t={e.t}: the log holds steps, "
                               "landmark frames, fixes and anchors only")

    # ------------------------------------------------------------------ helpers
    def _rejected(self, fix: GlobalFix, reason: str) -> FixOutcome:
        return self._counted(FixOutcome(fix, False, reason))

    def _counted(self, outcome: FixOutcome) -> FixOutcome:
        if outcome.accepted:
            self._count["n_fixes_accepted"] += 1
        else:
            self._count["n_fixes_rejected"] += 1
            key = outcome.reason.split(" ")[0] if outcome.reason else "unknown"
            self._reject_reasons[key] = self._reject_reasons.get(key, 0) + 1
            log.info("fix at t_meas=%.3f s rejected: %s", outcome.fix.t_meas, outcome.reason)
        return outcome

    def _T(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self._s.R_world_base
        T[:3, 3] = self._s.p_world
        return T

    def _record(self) -> None:
        s, period = self._s, self.config.trajectory_period_s
        last = self._traj.last() if len(self._traj) else None
        if last is not None and last[0] != s.t and period > 0 and s.t - last[0] < period - _T_EPS:
            return  # (checked before the row is built: this runs at every step)
        row = np.concatenate(([s.t], self._T().ravel(), s.P[:POSE_DIM, :POSE_DIM].ravel()))
        if last is not None and last[0] == s.t:
            last[:] = row
        else:
            self._traj.append(row)

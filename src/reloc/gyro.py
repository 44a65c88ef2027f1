"""Gyro monitor: a heading drift of the IMU that the landmarks do not see.

The back-ends take the rover's rotation from the IMU's orientation, whose yaw is integrated from
the gyro: a bias of ``b`` rad/s turns the heading by ``b`` every second. Their rotation noise
covers a healthy gyro (white, a few 1e-5 rad/s of bias); a bias step (a shock, a temperature
jump, a failing axis: the fault table's 0.002 rad/s, 410 deg/h) turns the heading by the same
sign every step, which white noise cannot represent and the landmarks only partly pull back
(docs/sim.md, "The fault-scenario table").

The monitor compares two frames of one landmark kind ``baseline_s`` apart (every kind exposes its
points in base_link, :class:`reloc.kinds.LandmarkObservations`). With ``R`` the IMU's rotation
of the current base_link in the reference one, a static landmark satisfies

    p_ref = Exp(delta u) R p_cur + d,    u = the gravity axis in the reference base_link,

where ``delta`` is the heading the IMU got wrong over the interval and ``d`` the translation.
The landmark pairs come from the slip monitor's translation-only registration
(:func:`reloc.slip.visual_translation`), tried over a few heading hypotheses, and ``(d, delta)``
from a weighted least-squares fit over the inlier pairs (:func:`visual_yaw`). Since the IMU's
reported rotation is ``Exp(b T u) R_true``, the bias over the interval ``T`` is ``b = -delta / T``,
with sigma ``sigma_delta / T`` (the fit's covariance times ``cov_scale``).

The decision pools the last ``confirm_checks`` determined checks of the kind (consecutive, no
two more than ``max_check_gap_s`` apart): their inverse-variance mean ``b_bar`` with sigma
``sigma_bar`` (a sparse field gives single checks of ~2-3 sigma at 0.002 rad/s; pooled, the
evidence adds up). The gyro is *biased* when those checks all have one sign, agree with each
other (``sum((b_i - b_bar)^2 / sigma_i^2)`` inside chi2(n - 1) at ``agree_p``, to start a
correction: one registration gone wrong, 8 sigma off on rocky-1km, does not carry an ordinary
check with it; a running correction's pool may disagree, as the bias changes) and ``|b_bar|``
exceeds both ``min_bias_radps`` and ``gate_sigma`` sigmas; then every odometry step's IMU
rotation is turned back by ``b_bar dt`` about the gravity axis (the orientations
``R_ref_base0``, ``R_ref_base1`` of every later step are premultiplied by the accumulated
correction, so roll and pitch stay the IMU's), and the step carries the estimate's uncertainty as
heading variance about the gravity axis, ``(sigma_bar^2 + change_sigma^2) dt T`` (correlated over
one check interval ``T``), plus once, at detection, the heading that went in uncorrected while
the checks confirmed it (``(b_bar T_pooled)^2``). The correction follows every later check, ends
at the first one whose pool no longer says *biased* (the checks compare the raw IMU, so they
measure the bias itself, not what is left of it), and after ``hold_s`` without a determined check.

The front-end correction serves both back-ends alike (the runner applies it after the slip
monitor's, before ``predict``). Core maths only: no I/O.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.stats import chi2

from reloc.config import Interval, NonNegative, Positive, PositiveInt, checked
from reloc.errors import ConfigError
from reloc.geometry import exp_so3
from reloc.odometry import OdometryStep
from reloc.slip import FrameReference, finite_points, visual_translation

log = logging.getLogger(__name__)

E_Z = np.array([0.0, 0.0, 1.0])

Fraction = Annotated[float, Interval(ge=0.0, le=1.0)]


@dataclass(frozen=True)
@checked(ConfigError)
class GyroConfig:
    """Settings of :class:`GyroMonitor` (see the module doc)."""

    enabled: bool = True
    baseline_s: Positive = 8.0  # frames compared at least this far apart
    max_baseline_s: Positive = 20.0  # a reference older than this (a gap) is replaced, not compared
    min_wheel_distance_m: NonNegative = 0.0  # the rover may turn on the spot: no distance needed
    # heading hypotheses (rad) tried for the pairs' registration: a bias of 0.002 rad/s turns the
    # landmarks at 5 m by 8 cm over 8 s, beyond the registration's cluster radius
    max_delta_rad: Positive = 0.06
    delta_step_rad: Positive = 0.01
    # the registration (reloc.slip.visual_translation)
    min_inliers: PositiveInt = 5
    inlier_chi2: Positive = 11.34
    ambiguity_ratio: Fraction = 0.6
    # translations looked for within search_margin_m + search_slip * |wheels| of the wheels' (the
    # whole segment from standing still, as the slip monitor searches, holds too many chance
    # clusters over seconds of motion; a stuck rover's checks go undetermined, the slip monitor's case)
    search_margin_m: NonNegative = 0.3
    search_slip: Fraction = 0.3
    # the fit's covariance is multiplied by this (pairs taken as independent): unscaled, its errors
    # against the truth were 0.75-1.02 / 1.84-2.06 / 2.1-3.0 sigma at the median / p90 / p99
    # (0.67 / 1.64 / 2.58 for a Gaussian; my2020 fault-free and bias step, rocky-1km and
    # cratered-3km 400 m, seed 0: `python -m fgslam.bench.gyro DIR`)
    cov_scale: Positive = 1.5
    # below this the back-ends' rotation noise covers the drift (a healthy gyro: ~1e-5 rad/s)
    min_bias_radps: NonNegative = 3.0e-4
    gate_sigma: Positive = 4.0
    confirm_checks: PositiveInt = 2  # determined checks pooled for a decision (all of one sign)
    max_check_gap_s: Positive = 40.0  # checks further apart than this are not pooled
    agree_p: Annotated[float, Interval(gt=0.0, lt=1.0)] = 0.99  # the pooled checks' homogeneity test
    change_sigma_radps: NonNegative = 1.0e-4  # how much the bias may change between two checks
    hold_s: Positive = 60.0  # a correction is dropped this long after the last check that measured it


@dataclass(frozen=True)
class VisualYaw:
    """Heading the IMU got wrong between two frames (``delta_rad``: the true rotation is the IMU's
    turned by ``delta`` about ``up``), its sigma, the translation ``d_m`` (3,) and the pairs used."""

    delta_rad: float
    sigma_rad: float
    d_m: np.ndarray
    n_inliers: int


def visual_yaw(p_ref: np.ndarray, cov_ref: np.ndarray, p_cur: np.ndarray, cov_cur: np.ndarray,
               R_ref_cur: np.ndarray, up: np.ndarray, d_wheel: np.ndarray, cfg: GyroConfig) -> VisualYaw | None:
    """The heading error of ``R_ref_cur`` (the IMU's rotation of the current base_link in the
    reference one) between a reference frame (points ``p_ref`` (N, 3), covariances ``cov_ref``)
    and the current one (``p_cur`` (M, 3), ``cov_cur``), about ``up`` (3,), the gravity axis in the
    reference base_link (see the module doc). None when no heading hypothesis registers."""
    p_ref, p_cur = np.asarray(p_ref, dtype=float), np.asarray(p_cur, dtype=float)
    cov_ref, cov_cur = np.asarray(cov_ref, dtype=float), np.asarray(cov_cur, dtype=float)
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    n_hyp = round(cfg.max_delta_rad / cfg.delta_step_rad)
    d_wheel = np.asarray(d_wheel, dtype=float)
    region = (d_wheel, cfg.search_margin_m + cfg.search_slip * float(np.linalg.norm(d_wheel)))
    best = None
    for k in sorted(range(-n_hyp, n_hyp + 1), key=abs):  # zero first: ties keep the smallest turn
        Rk = exp_so3(up * (k * cfg.delta_step_rad)) @ R_ref_cur
        vt = visual_translation(p_ref, cov_ref, p_cur, cov_cur, Rk, d_wheel, cfg, region)
        if vt is not None and (best is None or vt.n_inliers > best[1].n_inliers):
            best = (k * cfg.delta_step_rad, vt)
    if best is None:
        return None
    delta, vt = best
    i, j = vt.pairs[:, 0], vt.pairs[:, 1]
    d = vt.d_m
    cov = np.eye(4)
    for _ in range(3):  # Gauss-Newton on (d, delta) about the current heading
        R = exp_so3(up * delta) @ R_ref_cur
        q = p_cur[j] @ R.T
        C = cov_ref[i] + R @ cov_cur[j] @ R.T
        W = np.linalg.inv(C)
        J = np.zeros((len(i), 3, 4))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3] = np.cross(up, q)  # d(Exp(e u) q)/de = u x q
        r = p_ref[i] - q - d
        A = np.einsum("kai,kab,kbj->ij", J, W, J)
        b = np.einsum("kai,kab,kb->i", J, W, r)
        cov = np.linalg.inv(A)
        x = cov @ b
        d, delta = d + x[:3], delta + float(x[3])
    return VisualYaw(float(delta), math.sqrt(max(float(cov[3, 3]), 0.0)), d, len(i))


@dataclass(frozen=True)
class GyroCheck:
    """One determined check: its time and its reference frame's, the kind compared, the IMU's
    heading error over the interval (rad) and its sigma, the bias it implies (rad/s) and its sigma,
    the inlier pairs, and whether it detected a bias."""

    t: float
    t_ref: float
    kind: str
    delta_rad: float
    delta_sigma_rad: float
    bias_radps: float
    bias_sigma_radps: float
    n_inliers: int
    biased: bool


class GyroMonitor:
    """Stateful: ``correct`` every odometry step before the back-end predicts with it, ``observe``
    every landmark frame (see the module doc)."""

    def __init__(self, config: GyroConfig | None = None) -> None:
        self.cfg = config or GyroConfig()
        self._refs: dict[str, FrameReference] = {}
        self.bias = 0.0  # applied bias (rad/s about the gravity axis; 0: the IMU is trusted)
        self._psi = 0.0  # accumulated heading correction (rad) applied to the IMU's orientations
        self._extra_var_per_s = 0.0  # heading variance added per second while correcting
        self._pending_var = 0.0  # heading variance for the first corrected step
        self._active_until = -math.inf
        self._up = E_Z  # the gravity axis in base_link at the latest step
        self.checks: list[GyroCheck] = []
        self.n_undetermined = 0
        self.n_detections = 0
        self.corrected_s = 0.0
        self._pool: dict[str, list[tuple[float, float, float, float]]] = {}  # kind -> [(t, T, b, sigma)]

    @property
    def active(self) -> bool:
        return self.bias != 0.0

    def correct(self, step: OdometryStep) -> OdometryStep:
        """``step`` with its IMU orientations turned back by the accumulated correction and the
        estimate's uncertainty as heading variance while a bias is applied, else unchanged (but for
        a correction accumulated earlier). The raw IMU motion is integrated into every kind's
        reference first."""
        if not self.cfg.enabled:
            return step
        self._up = np.asarray(step.R_ref_base1, dtype=float)[2, :]  # R^T e_z
        FrameReference.advance_all(self._refs.values(), step, step.dR_base)
        if self.active and step.t1 > self._active_until:
            log.info("gyro bias correction ends at t=%.2f s: no check measured it for %.1f s", step.t1, self.cfg.hold_s)
            self._stop()
        psi0 = self._psi
        extra = 0.0
        if self.active:
            self._psi -= self.bias * step.dt
            self.corrected_s += step.dt
            extra, self._pending_var = self._extra_var_per_s * step.dt + self._pending_var, 0.0
        if psi0 == 0.0 and self._psi == 0.0:
            return step
        return dataclasses.replace(
            step,
            R_ref_base0=exp_so3(E_Z * psi0) @ step.R_ref_base0,
            R_ref_base1=exp_so3(E_Z * self._psi) @ step.R_ref_base1,
            extra_yaw_var_rad2=step.extra_yaw_var_rad2 + extra)

    def observe(self, kind: str, obs) -> GyroCheck | None:
        """One frame of landmark kind ``kind`` (its points in base_link): when its reference is
        ``baseline_s`` old, compare them and update the applied bias; the frame then becomes the
        reference (as it does when there is none, or the last one is too old)."""
        if not self.cfg.enabled:
            return None
        t = float(obs.t)
        ref = self._refs.get(kind)
        if ref is not None and t - ref.t < self.cfg.baseline_s:
            return None
        xyz, cov = finite_points(obs)
        check = None
        if (ref is not None and t - ref.t <= self.cfg.max_baseline_s
                and float(np.linalg.norm(ref.d)) >= self.cfg.min_wheel_distance_m):
            vy = visual_yaw(ref.xyz, ref.cov, xyz, cov, ref.R, ref.up, ref.d, self.cfg)
            if vy is None:
                self.n_undetermined += 1
            else:
                check = self._decide(t, ref.t, kind, vy)
        self._refs[kind] = FrameReference(t, xyz, cov, up=self._up.copy())
        return check

    def stats(self) -> dict:
        """Counters of the run: checks, undetermined comparisons, bias spells, corrected time, and
        the largest bias measured."""
        biases = [abs(c.bias_radps) for c in self.checks if c.biased]
        return {
            "enabled": self.cfg.enabled,
            "n_checks": len(self.checks),
            "n_undetermined": self.n_undetermined,
            "n_biased_checks": len(biases),
            "n_detections": self.n_detections,
            "corrected_s": round(self.corrected_s, 3),
            "max_bias_radps": round(max(biases), 6) if biases else 0.0,
        }

    # ---------------------------------------------------------------- internals
    def _decide(self, t: float, t_ref: float, kind: str, vy: VisualYaw) -> GyroCheck:
        cfg = self.cfg
        T = t - t_ref
        b = -vy.delta_rad / T
        sigma = vy.sigma_rad * math.sqrt(cfg.cov_scale) / T
        pool = self._pool.setdefault(kind, [])
        if pool and t_ref - pool[-1][0] > cfg.max_check_gap_s:
            pool.clear()
        pool.append((t, T, b, sigma))
        del pool[:-cfg.confirm_checks]
        w = np.array([1.0 / p[3] ** 2 for p in pool])
        bs = np.array([p[2] for p in pool])
        b_bar = float(w @ bs / w.sum())
        s_bar = float(1.0 / math.sqrt(w.sum()))
        agree = float(w @ (bs - b_bar) ** 2) <= chi2.ppf(cfg.agree_p, len(pool) - 1) if len(pool) > 1 else True
        biased = (len(pool) == cfg.confirm_checks and bool(np.all(np.sign(bs) == np.sign(b_bar)))
                  and (agree or self.active) and abs(b_bar) > max(cfg.min_bias_radps, cfg.gate_sigma * s_bar))
        check = GyroCheck(t, t_ref, kind, vy.delta_rad, vy.sigma_rad * math.sqrt(cfg.cov_scale), b, sigma,
                          vy.n_inliers, biased)
        self.checks.append(check)
        if biased:
            if not self.active:
                self.n_detections += 1
                # the heading the pooled checks saw drift went in uncorrected: its size, once, as
                # heading variance of the next corrected step
                self._pending_var = (b_bar * sum(p[1] for p in pool)) ** 2
                log.info("gyro bias %.2e rad/s (+- %.1e) detected at t=%.2f s by %s over %d checks", b_bar, s_bar, t,
                         kind, len(pool))
            self.bias = b_bar if b_bar != 0.0 else 1e-15
            self._extra_var_per_s = (s_bar**2 + cfg.change_sigma_radps**2) * T
            self._active_until = t + cfg.hold_s
        elif self.active:
            log.info("gyro bias ends at t=%.2f s (%s: %.2e rad/s +- %.1e pooled)", t, kind, b_bar, s_bar)
            self._stop()
        return check

    def _stop(self) -> None:
        self._pending_var = 0.0
        self.bias = 0.0
        self._extra_var_per_s = 0.0
        self._active_until = -math.inf

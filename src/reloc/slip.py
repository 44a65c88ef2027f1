"""Wheel-slip monitor: commanded motion that the landmarks do not see.

Wheels on loose soil can turn without moving the rover (100 % slip when it is stuck). The
odometry then says the rover drove while it stood still. The back-ends model slip as a few
per cent of the distance (``sigma * sqrt(distance)``), which cannot cover a rover that spins its
wheels in place for a minute: a smoother that associates landmarks from its odometry prediction
then loses them and follows the wheels (iSAM2 ended 0.5-0.8 m off after 60 s stuck on my2020,
docs/sim.md, "The fault-scenario table").

The monitor compares two frames of one landmark kind (every kind exposes its points in base_link,
:class:`reloc.kinds.LandmarkObservations`): the rotation between them comes from the IMU, so the
landmarks' displacement in the body frame gives the rover's *visual translation* over the
interval (:func:`visual_translation`, a translation-only registration that needs no map and no
association). Where the wheels turned at least ``min_wheel_distance_m``, the slip ratio is

    s = 1 - (d_visual . u) / |d_wheel|,   u = d_wheel / |d_wheel|,

with the sigma of the visual translation along ``u``. A check *detects slip* when ``|s|`` exceeds
both ``min_slip`` (below it the back-ends' own slip noise covers the error) and ``gate_sigma``
sigmas (the registration's covariance scaled by ``visual_cov_scale``, measured); after
``confirm_checks`` consecutive such checks (the slip they saw, uncorrected, is added once as
variance), every odometry step's forward speed is scaled by ``1 - s`` and its forward
variance grows by ``(sigma_s^2 + change_sigma^2) * d * L`` (``d`` the step's wheel distance, ``L``
the wheel distance of the check that measured ``s``: the slip is taken as correlated over one check
interval, so over ``L`` the added sigma is ``sqrt(sigma_s^2 + change_sigma^2) * L``), until a check
finds the wheels and the landmarks agreeing again, or ``hold_s`` passes without a determined check
(the rover is trusted to its wheels again: a camera that goes blind while stuck does not hold the
correction forever).

The front-end correction serves both back-ends alike (the runner applies it between the
odometry assembler and ``predict``). Core maths only: no I/O.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Annotated, Protocol

import numpy as np
from scipy.spatial import cKDTree

from reloc.config import Interval, NonNegative, Positive, PositiveInt, checked
from reloc.errors import ConfigError
from reloc.odometry import OdometryStep, step_translation

log = logging.getLogger(__name__)

Fraction = Annotated[float, Interval(ge=0.0, le=1.0)]


@dataclass(frozen=True)
@checked(ConfigError)
class SlipConfig:
    """Settings of :class:`SlipMonitor` (see the module doc)."""

    enabled: bool = True
    min_wheel_distance_m: Positive = 0.1  # wheels turned at least this between the frames compared
    max_frame_gap_s: Positive = 5.0  # frames further apart than this are not compared
    min_inliers: PositiveInt = 5  # landmark pairs that must agree on the visual translation
    # pair residual (Mahalanobis, 3 dof) of an inlier; 11.34 is chi2(3) at 0.99
    inlier_chi2: Positive = 11.34
    # a second cluster of pairs, away from the best one, holding this fraction of its inliers
    # makes the registration ambiguous (no decision)
    ambiguity_ratio: Fraction = 0.6
    search_margin_m: NonNegative = 0.3  # visual translations looked for up to this beyond [0, d_wheel]
    min_slip: Fraction = 0.3
    gate_sigma: Positive = 3.0
    # the visual translation's covariance (a weighted mean over pairs taken as independent) is
    # multiplied by this: on plains-2km (seed 0, 8727 determined checks) its errors against the
    # truth were 0.98 / 2.0 / 4.9 sigma at the median / p90 / p99 (0.67 / 1.64 / 2.58 for a
    # Gaussian), and 45 checks "saw" 30-91 % slip where the truth slipped under 10 %
    visual_cov_scale: Positive = 2.25
    # consecutive slipping checks (same sign) before a correction starts: a stuck rover stays
    # stuck, a chance registration error does not repeat
    confirm_checks: PositiveInt = 2
    change_sigma: NonNegative = 0.3  # how much the slip ratio may change between two checks
    max_skid: Fraction = 0.5  # the slip ratio applied is clipped to [-max_skid, 1]
    hold_s: Positive = 5.0  # a detected slip is applied this long after the last check that measured it


class Registration(Protocol):
    """The settings :func:`visual_translation` reads (:class:`SlipConfig`, :class:`reloc.gyro.GyroConfig`)."""

    min_inliers: int
    inlier_chi2: float
    ambiguity_ratio: float
    search_margin_m: float


@dataclass(frozen=True)
class VisualTranslation:
    """Translation ``d_m`` (3,) of base_link between two frames, in the first frame's base_link,
    its covariance ``cov_m2`` (3, 3), the number of landmark pairs behind it and those pairs
    (``pairs`` (k, 2): reference and current point indices)."""

    d_m: np.ndarray
    cov_m2: np.ndarray
    n_inliers: int
    pairs: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2), dtype=int))


def visual_translation(
    p_ref: np.ndarray,
    cov_ref: np.ndarray,
    p_cur: np.ndarray,
    cov_cur: np.ndarray,
    R_ref_cur: np.ndarray,
    d_wheel: np.ndarray,
    cfg: Registration,
    region: tuple[np.ndarray, float] | None = None,
) -> VisualTranslation | None:
    """The rover's translation between a reference frame (points ``p_ref`` (N, 3), covariances
    ``cov_ref`` (N, 3, 3), base_link then) and the current one (``p_cur`` (M, 3), ``cov_cur``),
    with ``R_ref_cur`` the rotation of the current base_link in the reference one (IMU) and
    ``d_wheel`` (3,) the wheels' translation (only bounding the search: anything from standing
    still to ``search_margin_m`` beyond the wheels' motion; ``region`` (centre (3,), radius m)
    replaces that ball).

    A static landmark seen in both frames satisfies ``p_ref = R p_cur + d``: every pair (i, j)
    proposes ``d = p_ref_i - R p_cur_j``; the densest cluster of proposals (pairs within their
    3-sigma radius) is refined by a weighted mean over one-to-one inlier pairs. None when fewer
    than ``min_inliers`` pairs agree or a second cluster is nearly as strong (ambiguous)."""
    p_ref, p_cur = np.asarray(p_ref, dtype=float), np.asarray(p_cur, dtype=float)
    if len(p_ref) < cfg.min_inliers or len(p_cur) < cfg.min_inliers:
        return None
    q = p_cur @ R_ref_cur.T
    cq = R_ref_cur @ np.asarray(cov_cur, dtype=float) @ R_ref_cur.T
    # search region: the segment from standing still to the wheels' translation, widened
    if region is None:
        centre = 0.5 * np.asarray(d_wheel, dtype=float)
        radius = float(np.linalg.norm(centre)) + cfg.search_margin_m
    else:
        centre, radius = np.asarray(region[0], dtype=float), float(region[1])
    D, ii, jj = _pairs_in_region(p_ref, q, centre, radius)
    if ii.size < cfg.min_inliers:
        return None
    var = (np.trace(cov_ref, axis1=1, axis2=2)[ii] + np.trace(cq, axis1=1, axis2=2)[jj]) / 3.0
    r = math.sqrt(cfg.inlier_chi2) * math.sqrt(float(np.median(var)))
    tree = cKDTree(D)
    counts = tree.query_ball_point(D, r, return_length=True)
    best = int(np.argmax(counts))
    if counts[best] < cfg.min_inliers:
        return None
    d = D[best]
    C_pair = np.asarray(cov_ref, dtype=float)[ii] + cq[jj]
    W_pair = np.linalg.inv(C_pair)
    inl = np.zeros(0, dtype=int)
    for _ in range(3):  # inliers by Mahalanobis residual, one-to-one, then a weighted mean
        e = D - d
        chi2 = np.einsum("ki,kij,kj->k", e, W_pair, e)
        inl = _one_to_one(np.flatnonzero(chi2 <= cfg.inlier_chi2), chi2, ii, jj)
        if inl.size < cfg.min_inliers:
            return None
        info = W_pair[inl].sum(axis=0)
        cov = np.linalg.inv(info)
        d = cov @ np.einsum("kij,kj->i", W_pair[inl], D[inl])
    far = np.linalg.norm(D - d, axis=1) > 2.0 * r
    if far.any() and np.max(np.asarray(counts)[far]) >= cfg.ambiguity_ratio * inl.size:
        return None
    return VisualTranslation(d, 0.5 * (cov + cov.T), int(inl.size), np.column_stack([ii[inl], jj[inl]]))


def _pairs_in_region(p_ref: np.ndarray, q: np.ndarray, centre: np.ndarray, radius: float):
    """The proposals ``D = p_ref[i] - q[j]`` within ``radius`` of ``centre``, with their ``i`` and
    ``j``, in row-major (i, j) order. Of the N x M pairs (~12,000 a frame) a few hundred fall in
    the region: a k-d tree of ``p_ref`` queried at ``q + centre`` finds them (with a nanometre of
    margin), and the region test proper is then applied to those, so the result is the one the
    whole N x M array gives, bit for bit."""
    lists = cKDTree(p_ref).query_ball_point(q + centre, radius + 1e-9)
    n = np.fromiter((len(v) for v in lists), dtype=int, count=len(lists))
    jj = np.repeat(np.arange(len(q)), n)
    ii = np.fromiter((i for v in lists for i in v), dtype=int, count=int(n.sum()))
    order = np.lexsort((jj, ii))
    ii, jj = ii[order], jj[order]
    D = p_ref[ii] - q[jj]
    keep = np.linalg.norm(D - centre, axis=1) <= radius
    return D[keep], ii[keep], jj[keep]


def _one_to_one(cand: np.ndarray, cost: np.ndarray, ii: np.ndarray, jj: np.ndarray) -> np.ndarray:
    """The lowest-cost subset of pairs ``cand`` in which no point of either frame appears twice."""
    used_i: set[int] = set()
    used_j: set[int] = set()
    out = []
    for k in cand[np.argsort(cost[cand], kind="stable")]:
        if ii[k] in used_i or jj[k] in used_j:
            continue
        used_i.add(int(ii[k]))
        used_j.add(int(jj[k]))
        out.append(k)
    return np.array(out, dtype=int)


@dataclass
class FrameReference:
    """A kind's reference frame (its points and covariances in base_link then) and the motion
    since it: the current base_link's rotation ``R`` in the reference one and the wheels'
    translation ``d`` (IMU rotation, commanded distance). Shared with :mod:`reloc.gyro`."""

    t: float
    xyz: np.ndarray
    cov: np.ndarray
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))  # current base in the reference base
    d: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))  # wheels' translation
    up: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # gravity axis then

    @staticmethod
    def advance_all(refs, step: OdometryStep, dR: np.ndarray) -> None:
        """Integrate one raw odometry step (its rotation ``dR``) into every reference of ``refs``."""
        if refs:
            d = step_translation(step, dR)
            for ref in refs:
                ref.d = ref.d + ref.R @ d
                ref.R = ref.R @ dR


def finite_points(obs) -> tuple[np.ndarray, np.ndarray]:
    """A landmark frame's points (N, 3) and covariances (N, 3, 3) in base_link, non-finite rows dropped."""
    xyz = np.asarray(obs.xyz_base_m, dtype=float).reshape(-1, 3)
    cov = np.asarray(obs.cov_base_m2, dtype=float).reshape(-1, 3, 3)
    finite = np.isfinite(xyz).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    return xyz[finite], cov[finite]


@dataclass(frozen=True)
class SlipCheck:
    """One determined check: its time and its reference frame's, the kind compared, wheel and
    visual distance (m), the slip ratio and its sigma, the inlier pairs, and whether it detected
    slip."""

    t: float
    t_ref: float
    kind: str
    wheel_m: float
    visual_m: float
    slip: float
    slip_sigma: float
    n_inliers: int
    slipping: bool


class SlipMonitor:
    """Stateful: ``correct`` every odometry step before the back-end predicts with it, ``observe``
    every landmark frame (see the module doc)."""

    def __init__(self, config: SlipConfig | None = None) -> None:
        self.cfg = config or SlipConfig()
        self._refs: dict[str, FrameReference] = {}
        self.slip = 0.0  # applied slip ratio (0: the wheels are trusted)
        self._extra_var_per_m = 0.0  # forward variance added per metre of wheel motion
        self._active_until = -math.inf
        self.checks: list[SlipCheck] = []
        self.n_undetermined = 0  # comparisons without a determined visual translation
        self.n_detections = 0  # checks that started a slip spell
        self.corrected_s = 0.0  # stream time under correction
        self._streak, self._streak_sign = 0, 1.0  # consecutive slipping checks, and their sign
        self._streak_wheel_m = 0.0  # the wheel distance of those checks
        self._pending_var = 0.0  # forward variance for the first corrected step

    @property
    def active(self) -> bool:
        return self.slip != 0.0

    def correct(self, step: OdometryStep) -> OdometryStep:
        """``step`` with its forward speed scaled by ``1 - slip`` and the slip's uncertainty as
        forward variance while a slip is applied, else unchanged. The wheels' own motion is
        integrated into every kind's reference first."""
        if not self.cfg.enabled:
            return step
        dist = step.v_mps * step.dt
        if self._refs:
            FrameReference.advance_all(self._refs.values(), step, step.dR_base)
        if not self.active:
            return step
        if step.t1 > self._active_until:
            log.info("wheel slip correction ends at t=%.2f s: no check measured it for %.1f s",
                     step.t1, self.cfg.hold_s)
            self._stop()
            return step
        self.corrected_s += step.dt
        extra, self._pending_var = self._extra_var_per_m * abs(dist) + self._pending_var, 0.0
        return dataclasses.replace(step, v_mps=step.v_mps * (1.0 - self.slip),
                                   extra_forward_var_m2=step.extra_forward_var_m2 + extra)

    def observe(self, kind: str, obs) -> SlipCheck | None:
        """One frame of landmark kind ``kind`` (its points in base_link): compare it with the
        kind's reference frame and update the applied slip; the frame becomes the reference
        (unless the wheels have not yet turned enough to compare)."""
        if not self.cfg.enabled:
            return None
        xyz, cov = finite_points(obs)
        t = float(obs.t)
        ref = self._refs.get(kind)
        check = None
        if ref is not None and t - ref.t <= self.cfg.max_frame_gap_s:
            wheel = float(np.linalg.norm(ref.d))
            if wheel < self.cfg.min_wheel_distance_m:
                return None  # keep the reference: not enough wheel motion yet
            vt = visual_translation(ref.xyz, ref.cov, xyz, cov, ref.R, ref.d, self.cfg)
            if vt is None:
                self.n_undetermined += 1
            else:
                check = self._decide(t, ref.t, kind, ref.d, vt)
        self._refs[kind] = FrameReference(t, xyz, cov)
        return check

    def stats(self) -> dict:
        """Counters of the run: checks, undetermined comparisons, slip spells, corrected time,
        and the largest slip measured."""
        slips = [c.slip for c in self.checks if c.slipping]
        return {
            "enabled": self.cfg.enabled,
            "n_checks": len(self.checks),
            "n_undetermined": self.n_undetermined,
            "n_slipping_checks": len(slips),
            "n_detections": self.n_detections,
            "corrected_s": round(self.corrected_s, 3),
            "max_slip": round(max(slips), 4) if slips else 0.0,
        }

    # ---------------------------------------------------------------- internals
    def _decide(self, t: float, t_ref: float, kind: str, d_wheel: np.ndarray, vt: VisualTranslation) -> SlipCheck:
        cfg = self.cfg
        wheel = float(np.linalg.norm(d_wheel))
        u = d_wheel / wheel
        s = 1.0 - float(vt.d_m @ u) / wheel
        sigma = math.sqrt(max(float(u @ vt.cov_m2 @ u), 0.0) * cfg.visual_cov_scale) / wheel
        slipping = abs(s) > max(cfg.min_slip, cfg.gate_sigma * sigma)
        check = SlipCheck(t, t_ref, kind, wheel, float(np.linalg.norm(vt.d_m)), s, sigma, vt.n_inliers, slipping)
        self.checks.append(check)
        same = slipping and (self._streak == 0 or s * self._streak_sign > 0)
        self._streak = self._streak + 1 if same else int(slipping)
        self._streak_wheel_m = (self._streak_wheel_m + wheel if same else wheel) if slipping else 0.0
        self._streak_sign = math.copysign(1.0, s)
        if slipping and (self.active or self._streak >= cfg.confirm_checks):
            if not self.active:
                self.n_detections += 1
                # the slip of the checks that confirmed it went in uncorrected: its size, once, as
                # variance of the next corrected step
                self._pending_var = (s * self._streak_wheel_m) ** 2
                log.info("wheel slip %.0f %% (+- %.0f %%) detected at t=%.2f s by %s: wheels %.2f m, "
                         "landmarks %.2f m", 100 * s, 100 * sigma, t, kind, wheel, check.visual_m)
            self.slip = float(np.clip(s, -cfg.max_skid, 1.0))
            if self.slip == 0.0:  # exactly 0 would read as inactive
                self.slip = 1e-12
            self._extra_var_per_m = (sigma**2 + cfg.change_sigma**2) * wheel
            self._active_until = t + cfg.hold_s
        elif not slipping and self.active:
            log.info("wheel slip ends at t=%.2f s (%s: wheels %.2f m, landmarks %.2f m)", t, kind, wheel,
                     check.visual_m)
            self._stop()
        return check

    def _stop(self) -> None:
        self._pending_var = 0.0
        self.slip = 0.0
        self._extra_var_per_m = 0.0
        self._active_until = -math.inf

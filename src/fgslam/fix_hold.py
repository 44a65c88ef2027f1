"""A far fix waits for a second one that agrees with it.

A back-end's own gates judge a fix against the back-end's covariance. On a route where the
estimate has drifted metres and knows it, that covariance also admits a confidently wrong fix a
few metres from the truth: the gates cannot tell the two apart (docs/app.md, "On a drifted route
the goal fails": iSAM2 + reloc took 12 of 32 wrong fixes on sparse-5km seed 1). What does tell
them apart is a second fix. Right fixes agree with each other through the odometry between them;
wrong ones (a repetitive rock field, a wrong catalog entry) each point somewhere else.

:class:`FarFixHold` wraps a back-end. A fix whose position is within ``beyond_m`` of the
estimate at its ``t_meas`` goes to the back-end as it comes (the usual case: the estimate is
metres better than that wherever fixes keep coming). A fix further away is *held*: its outcome
says so, and nothing reaches the back-end. When a later far fix agrees with a held one, both
(every held fix it agrees with, oldest first, then the new one) go to the back-end, whose gates
then decide as usual; their outcomes replace the held ones (:func:`settle`). A held fix that no
fix agrees with within ``max_age_s`` is dropped, its outcome left as held.

Agreement is judged on positions, through the odometry alone: with ``D(t)`` the planar
dead-reckoned path of the odometry steps the back-end was given (:class:`OdometryPath`, unmoved
by any correction) and ``psi`` the turn from its frame to the estimate's, two fixes ``F1`` at
``t1`` and ``F2`` at ``t2`` agree when ``r = (F2 - F1) - R(psi) (D(t2) - D(t1))`` is inside the
chi-square gate ``agree_chi2`` (2 dof) of ``C1 + C2 + (drift_fraction s)^2 I + var(yaw) q q^T``:
the fixes' own position covariances (each fix alone: without the correlation factor its
producer widened it by for fusion, :meth:`reloc.measurements.GlobalFix.split_cov`), the
odometry's drift over the distance ``s`` driven between them, and the estimate's heading
uncertainty swinging the displacement ``d`` (``q`` = ``d`` turned 90 deg). The fixes' headings
are not used: a fix from one identified crater carries none worth the name (0.5 rad).

A back-end that is lost (:class:`fgslam.backends.reanchor.Reanchoring` before its first fix)
takes every fix as it comes: its re-anchoring is the relocalizer's whole-catalog search's to
decide. ``beyond_m: 0`` turns the hold off.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from fgslam.errors import FgslamError
from reloc.backend import Backend, BackendStats, FixOutcome
from reloc.config import NonNegative, Positive, PositiveInt, checked
from reloc.geometry import wrap_angle, yaw_of
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep
from reloc.procrustes import rotation_2d

log = logging.getLogger(__name__)

HELD = "held"  # first word of a held fix's reason


class FixHoldError(FgslamError):
    """A fix-hold setting is out of range."""


@dataclass(frozen=True)
@checked(FixHoldError)
class FixHoldConfig:
    """Settings of :class:`FarFixHold` (see the module doc)."""

    # a fix further than this from the estimate at its t_meas waits for a second that agrees
    # (0: every fix goes to the back-end as it comes). Wrong fixes are 5-50 m off in the
    # wrong-fix bench; an estimate that fixes keep is far better than 3 m
    beyond_m: NonNegative = 3.0
    agree_chi2: Positive = 9.21  # chi-square gate (2 dof, 0.99) on two fixes' disagreement
    drift_fraction: NonNegative = 0.03  # the odometry's position drift per metre driven between two fixes
    floor_m: NonNegative = 0.1  # a floor on the disagreement's sigma, per axis
    max_age_s: Positive = 90.0  # a held fix older than this (relative to a new fix) is dropped
    max_held: PositiveInt = 32  # held fixes kept at most (the oldest dropped first)


class OdometryPath:
    """The planar dead-reckoned path (x, y, yaw, distance driven) of odometry steps, kept
    ``horizon_s`` back; its frame is its own (the first step's heading, at the origin)."""

    def __init__(self, horizon_s: float) -> None:
        self.horizon_s = float(horizon_s)
        self._t: list[float] = []
        self._p: list[tuple[float, float, float, float]] = []

    def add(self, step: OdometryStep) -> None:
        """Append ``step``: its forward distance along base_link x (mean of the step's two
        orientations, projected on the plane), its heading the IMU's at ``t1``."""
        if not self._t:
            self._t.append(float(step.t0))
            self._p.append((0.0, 0.0, float(yaw_of(step.R_ref_base0)), 0.0))
        x, y, _, s = self._p[-1]
        dist = float(step.v_mps) * float(step.dt)
        ax = 0.5 * (np.asarray(step.R_ref_base0)[:2, 0] + np.asarray(step.R_ref_base1)[:2, 0])
        self._t.append(float(step.t1))
        self._p.append((x + dist * float(ax[0]), y + dist * float(ax[1]), float(yaw_of(step.R_ref_base1)), s + abs(dist)))
        if len(self._t) % 4096 == 0:  # forget what is older than the horizon, now and then
            cut = bisect.bisect_left(self._t, self._t[-1] - self.horizon_s) - 1
            if cut > 0:
                del self._t[:cut], self._p[:cut]

    def at(self, t: float) -> np.ndarray | None:
        """(4,) x, y, yaw, distance at ``t`` (linear between steps; the newest after it); None
        before the path kept."""
        if not self._t or t < self._t[0] - 1e-9:
            return None
        i = bisect.bisect_left(self._t, t)
        if i >= len(self._t):
            return np.array(self._p[-1])
        if i == 0 or self._t[i] == t:
            return np.array(self._p[i])
        t0, t1 = self._t[i - 1], self._t[i]
        a, b = np.array(self._p[i - 1]), np.array(self._p[i])
        w = (t - t0) / (t1 - t0)
        out = a + w * (b - a)
        out[2] = a[2] + w * float(wrap_angle(b[2] - a[2]))
        return out


@dataclass
class _Held:
    fix: GlobalFix
    odo: np.ndarray  # OdometryPath.at(t_meas)


class FarFixHold(Backend):
    """``inner`` with far fixes held until a second agrees (module doc); the rest is ``inner``'s."""

    def __init__(self, inner: Backend, config: FixHoldConfig | None = None) -> None:
        self.inner = inner
        self.hold = config or FixHoldConfig()
        self.path = OdometryPath(self.hold.max_age_s + 60.0)
        self._held: list[_Held] = []
        self.counts = {"held": 0, "released": 0, "dropped": 0}
        self.waits_s: list[float] = []  # how long each released fix waited for its second

    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def config(self):
        return self.inner.config

    @property
    def relative_cost(self) -> float:
        return self.inner.relative_cost

    def __getattr__(self, name: str):  # the rest of the wrapped back-end (re-anchorings, counters)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def predict(self, step: OdometryStep) -> None:
        self.inner.predict(step)
        self.path.add(step)

    def observe(self, obs):
        return self.inner.observe(obs)

    def expect_fix(self, t_meas: float) -> None:
        self.inner.expect_fix(t_meas)

    def estimate(self):
        return self.inner.estimate()

    def landmark_map(self, kind: str):
        return self.inner.landmark_map(kind)

    def trajectory(self):
        return self.inner.trajectory()

    def stats(self) -> BackendStats:
        s = self.inner.stats()
        waits = np.asarray(self.waits_s, dtype=float)
        hold = {**self.counts, "waiting": len(self._held),
                "wait_s_max": float(waits.max()) if waits.size else 0.0,
                "wait_s_median": float(np.median(waits)) if waits.size else 0.0}
        return dataclasses.replace(s, extra={**s.extra, "fix_hold": hold})

    def apply_fix(self, fix: GlobalFix) -> FixOutcome:
        cfg = self.hold
        if cfg.beyond_m <= 0 or getattr(self.inner, "lost", False):
            return self.inner.apply_fix(fix)
        self._forget_before(fix.t_meas - cfg.max_age_s)
        est = self.inner.estimate()
        now, then = self.path.at(est.t), self.path.at(fix.t_meas)
        if now is None or then is None:  # no odometry yet, or the fix is older than the path kept
            return self.inner.apply_fix(fix)
        R = rotation_2d(est.yaw_rad - now[2])  # the odometry's frame -> the estimate's
        expected = est.position_m[:2] + R @ (then[:2] - now[:2])
        distance = float(np.hypot(*(np.array([fix.x_m, fix.y_m]) - expected)))
        if distance <= cfg.beyond_m:
            return self.inner.apply_fix(fix)
        var_yaw = float(est.cov[5, 5])
        agreeing = [h for h in self._held if self._agree(h, fix, then, R, var_yaw)]
        if not agreeing:
            self._held.append(_Held(fix, then))
            if len(self._held) > cfg.max_held:
                self._held.pop(0)
                self.counts["dropped"] += 1
            self.counts["held"] += 1
            log.info("fix at t=%.2f held: %.1f m from the estimate", fix.t_meas, distance)
            return FixOutcome(fix, False, f"{HELD}: {distance:.1f} m from the estimate (beyond {cfg.beyond_m:.1f} m), "
                                          "no second fix agreed")
        self._held = [h for h in self._held if h not in agreeing]
        self.counts["released"] += len(agreeing)
        log.info("fix at t=%.2f (%.1f m from the estimate) agrees with %d held: applied together",
                 fix.t_meas, distance, len(agreeing))
        released = tuple(dataclasses.replace(self.inner.apply_fix(h.fix), t_applied=fix.t_recv)
                         for h in sorted(agreeing, key=lambda h: h.fix.t_meas))
        self.waits_s.extend(fix.t_recv - h.fix.t_recv for h in agreeing)
        return dataclasses.replace(self.inner.apply_fix(fix), released=released)

    def _agree(self, h: _Held, fix: GlobalFix, odo: np.ndarray, R: np.ndarray, var_yaw: float) -> bool:
        cfg = self.hold
        d = R @ (odo[:2] - h.odo[:2])  # the estimate's displacement between the two t_meas
        r = np.array([fix.x_m - h.fix.x_m, fix.y_m - h.fix.y_m]) - d
        q = np.array([-d[1], d[0]])
        drift = cfg.drift_fraction * abs(float(odo[3] - h.odo[3]))
        S = (_alone_xy(h.fix) + _alone_xy(fix) + (drift**2 + cfg.floor_m**2) * np.eye(2) + var_yaw * np.outer(q, q))
        try:
            d2 = float(r @ np.linalg.solve(S, r))
        except np.linalg.LinAlgError:
            return False
        return d2 <= cfg.agree_chi2

    def _forget_before(self, t: float) -> None:
        old = [h for h in self._held if h.fix.t_meas < t]
        if old:
            self.counts["dropped"] += len(old)
            self._held = [h for h in self._held if h.fix.t_meas >= t]


def _alone_xy(fix: GlobalFix) -> np.ndarray:
    """(2, 2) position covariance of ``fix`` alone: its match's and the rover-relative part, without
    the producer's correlation factor (which widens a fix for fusing it beside others it shares
    errors with, up to 100x on a long route's crater fixes, and would let a wrong fix agree)."""
    match, rel = fix.split_cov()
    return (match + rel)[:2, :2]


def hold_far_fixes(backend: Backend, config: FixHoldConfig) -> Backend:
    """``backend`` wrapped by :class:`FarFixHold` (itself when ``beyond_m`` is 0)."""
    return backend if config.beyond_m <= 0 else FarFixHold(backend, config)


def settle(outcomes: list[FixOutcome], outcome: FixOutcome) -> list[FixOutcome]:
    """Append ``outcome`` to ``outcomes``, each of its ``released`` outcomes replacing the held
    outcome of the same fix in place; the outcomes decided now (released ones first)."""
    for r in outcome.released:
        for i in range(len(outcomes) - 1, -1, -1):
            if outcomes[i].fix is r.fix:
                outcomes[i] = r
                break
        else:
            outcomes.append(r)
    outcomes.append(dataclasses.replace(outcome, released=()) if outcome.released else outcome)
    return [*outcome.released, outcomes[-1]]

"""A far fix waits for a second that agrees (fgslam.fix_hold): the odometry path it is judged
through, the outcomes it settles, and both back-ends started metres off with wrong fixes among
the right ones."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ekf.slam import EkfSlam
from fgslam.compare import first_fix_s
from fgslam.fix_hold import FarFixHold, FixHoldConfig, FixHoldError, OdometryPath, settle
from fgslam.runner import RunnerConfig
from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.config import FixConfig
from fgslam.smoother.fixes import kernel_scale
from fgslam.smoother.synthetic import SyntheticConfig, drive, simulate_synthetic
from reloc.backend import FixOutcome, PoseEstimate
from reloc.config import config_from_dict
from reloc.errors import ConfigError
from reloc.measurements import GlobalFix
from reloc.odometry import OdometryStep


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_the_odometry_path_integrates_a_turning_drive():
    path = OdometryPath(horizon_s=1e9)
    yaw_rate, v, dt = 0.05, 0.2, 0.1
    for k in range(600):  # 60 s on a circle of radius v / yaw_rate = 4 m
        t0 = k * dt
        path.add(OdometryStep(t0, t0 + dt, v, yaw_rate, _rz(yaw_rate * t0), _rz(yaw_rate * (t0 + dt)), np.zeros(3)))
    for t in (0.0, 13.37, 60.0):
        x, y, yaw, s = path.at(t)
        assert (x, y) == pytest.approx((4.0 * np.sin(yaw_rate * t), 4.0 * (1 - np.cos(yaw_rate * t))), abs=2e-3)
        assert yaw == pytest.approx(np.arctan2(np.sin(yaw_rate * t), np.cos(yaw_rate * t)), abs=1e-9)
        assert s == pytest.approx(v * t, abs=1e-9)
    assert path.at(-1.0) is None


def test_settle_puts_a_released_outcome_in_place_of_the_held_one():
    cov = np.diag([0.1, 0.1, 0.01])
    f1, f2, f3 = (GlobalFix(t, t + 1.0, float(t), 0.0, 0.0, cov) for t in (1.0, 2.0, 3.0))
    out: list[FixOutcome] = []
    assert settle(out, FixOutcome(f1, False, "held: 6.0 m")) == [out[0]]
    settle(out, FixOutcome(f2, True))
    decided = settle(out, FixOutcome(f3, True, released=(FixOutcome(f1, True),)))
    assert [o.fix for o in out] == [f1, f2, f3]
    assert all(o.accepted for o in out) and not out[2].released
    assert [o.fix for o in decided] == [f1, f3]


def test_time_to_first_fix_counts_a_held_fixs_wait():
    cov = np.diag([0.1, 0.1, 0.01])
    held, second, later = (GlobalFix(t, t + 2.0, 0.0, 0.0, 0.0, cov) for t in (10.0, 20.0, 30.0))
    outcomes = [FixOutcome(held, True, t_applied=22.0), FixOutcome(second, True), FixOutcome(later, True)]
    assert first_fix_s(outcomes, 5.0) == [5.0, 17.0]  # measured at 10 s, given to the back-end at 22 s
    assert first_fix_s([FixOutcome(held, False, "held"), FixOutcome(later, True)], 5.0) == [25.0, 27.0]
    assert first_fix_s([FixOutcome(held, False, "held")], 5.0) is None


def test_the_config_is_checked():
    with pytest.raises(FixHoldError, match="beyond_m"):
        FixHoldConfig(beyond_m=-1.0)
    with pytest.raises(ConfigError, match="runner.fix_hold.agree_chi2"):
        config_from_dict(RunnerConfig, {"fix_hold": {"agree_chi2": 0.0}}, where="runner.")


@pytest.fixture(scope="module")
def run():
    return simulate_synthetic(SyntheticConfig(seed=11, duration_s=150.0))


OFF = np.array([6.0, 2.0])  # where the back-ends start, from the truth (m)


def _started_off(run) -> PoseEstimate:
    """The true start moved by OFF, its covariance a 3 m sigma that says so (drifted, not lost)."""
    T = run.initial_pose.T_world_base.copy()
    T[:2, 3] += OFF
    cov = run.initial_pose.cov.copy()
    cov[0, 0] = cov[1, 1] = 3.0**2
    return PoseEstimate(run.initial_pose.t, T, cov)


def _fixes(run) -> tuple[list[GlobalFix], set[float]]:
    """A right fix every 10 s from 20 s (0.3 m noise, claimed); wrong ones with the same claimed
    covariance: at 12 s, before any right one, 4.5 m from where the back-ends then think they
    are (inside their 3 m sigma, 7 m from the truth), and 5 s after each right one, moved 8-20 m
    in a random direction."""
    rng = np.random.default_rng(4)
    cov = np.diag([0.3**2, 0.3**2, 0.02**2])
    fixes, wrong = [], set()
    for t in np.arange(20.0, 141.0, 10.0):
        T = run.gt_at(t)
        yaw = float(np.arctan2(T[1, 0], T[0, 0]))
        fixes.append(GlobalFix(t, t + 2.0, T[0, 3] + rng.normal(0, 0.3), T[1, 3] + rng.normal(0, 0.3), yaw, cov))
        for tw in ((12.0, t + 5.0) if t == 20.0 else (t + 5.0,)):
            Tw = run.gt_at(tw)
            r, b = rng.uniform(8.0, 20.0), rng.uniform(-np.pi, np.pi)
            off = OFF + [0.0, 4.5] if tw == 12.0 else r * np.array([np.cos(b), np.sin(b)])
            fixes.append(GlobalFix(tw, tw + 2.0, Tw[0, 3] + off[0], Tw[1, 3] + off[1],
                                   float(np.arctan2(Tw[1, 0], Tw[0, 0])), cov))
            wrong.add(tw)
    return sorted(fixes, key=lambda f: f.t_recv), wrong


def _final_error(run, out) -> float:
    return float(np.linalg.norm(out.est_T[-1][:2, 3] - run.gt_at(out.est_t[-1])[:2, 3]))


@pytest.mark.parametrize("make", [lambda s: Isam2Smoother(s), lambda s: EkfSlam(s)], ids=["isam2", "ekf"])
def test_a_drifted_back_end_takes_the_right_far_fixes_and_none_of_the_wrong(run, make):
    fixes, wrong = _fixes(run)
    out = drive(make(_started_off(run)), run.measurements, fixes, hold=FixHoldConfig())
    assert len(out.outcomes) == len(fixes)  # one outcome per fix, the held ones settled in place
    by_t = {o.fix.t_meas: o for o in out.outcomes}
    assert not any(by_t[t].accepted for t in wrong), [by_t[t].reason for t in sorted(wrong)]
    assert all(by_t[t].reason.startswith("held") for t in wrong)
    first, second = by_t[20.0], by_t[30.0]
    assert first.accepted and second.accepted, (first.reason, second.reason)  # 6.3 m off: held, then agreed
    assert first.applied_s == second.fix.t_recv and second.applied_s == second.fix.t_recv  # it waited 10 s
    right = [o for t, o in by_t.items() if t not in wrong]
    assert sum(o.accepted for o in right) >= len(right) - 1
    assert _final_error(run, out) < 0.5


@pytest.mark.parametrize("make", [lambda s: Isam2Smoother(s), lambda s: EkfSlam(s)], ids=["isam2", "ekf"])
def test_without_the_hold_the_drifted_back_end_takes_wrong_fixes(run, make):
    """What the hold is for: the same fixes straight to the back-end's own gates. The first
    wrong one is inside the drifted back-end's covariance and goes in; the right ones are then
    9 m away and refused for the rest of the run."""
    fixes, _ = _fixes(run)
    out = drive(make(_started_off(run)), run.measurements, fixes, hold=FixHoldConfig(beyond_m=0.0))
    assert out.outcomes[0].fix.t_meas == 12.0 and out.outcomes[0].accepted
    assert _final_error(run, out) > 5.0


def test_a_fix_near_the_estimate_goes_straight_to_the_back_end(run):
    fixes, _ = _fixes(run)
    right = [f for f in fixes if f.t_meas % 10.0 == 0.0]
    be = FarFixHold(Isam2Smoother(run.initial_pose), FixHoldConfig())
    out = drive(be, run.measurements, right, hold=FixHoldConfig(beyond_m=0.0))
    assert all(o.accepted for o in out.outcomes), [o.reason for o in out.outcomes]
    assert be.stats().extra["fix_hold"] == {"held": 0, "released": 0, "dropped": 0, "waiting": 0,
                                            "wait_s_max": 0.0, "wait_s_median": 0.0}


def test_a_held_fix_no_second_agrees_with_is_dropped_after_max_age(run):
    fixes, wrong = _fixes(run)
    only_wrong = [f for f in fixes if f.t_meas in wrong]
    be = FarFixHold(Isam2Smoother(run.initial_pose), FixHoldConfig(max_age_s=25.0))
    out = drive(be, run.measurements, only_wrong, hold=FixHoldConfig(beyond_m=0.0))
    assert not any(o.accepted for o in out.outcomes)
    counts = be.stats().extra["fix_hold"]
    assert counts["held"] == len(only_wrong) and counts["released"] == 0
    assert counts["waiting"] <= 3 and counts["dropped"] == len(only_wrong) - counts["waiting"]


def test_a_lost_back_end_re_anchors_on_its_first_fix(run):
    """The hold leaves re-anchoring to the relocalizer's whole-catalog search."""
    from fgslam.backends.registry import make_backend

    start = _started_off(run)
    start = dataclasses.replace(start, cov=np.diag([50.0**2, 50.0**2, 0.01, 1e-4, 1e-4, 0.3**2]))
    fixes, _ = _fixes(run)
    be = FarFixHold(make_backend("isam2", start), FixHoldConfig())
    out = drive(be, run.measurements, fixes[:1], hold=FixHoldConfig(beyond_m=0.0))
    assert out.outcomes[0].accepted and out.outcomes[0].reason.startswith("re-anchored")


def test_the_kernel_scale_is_the_innovations_spread_over_the_fixs():
    R = np.diag([0.09, 0.04])
    assert kernel_scale(np.zeros((2, 2)), R) == pytest.approx(1.0)
    assert kernel_scale(np.diag([0.27, 0.04]), R) == pytest.approx(2.0)  # x: (0.27 + 0.09) / 0.09 = 4
    assert kernel_scale(np.diag([0.0, 0.32]), R) == pytest.approx(3.0)  # y: (0.32 + 0.04) / 0.04 = 9
    assert kernel_scale(np.eye(2), np.zeros((2, 2))) == 1.0  # no fix covariance to scale by: the kernel as set
    # beyond an estimate 3x as uncertain as the fix only: y: lambda 99, (1 + 99) / (1 + 3^2) = 10; 1 up to it
    assert kernel_scale(np.diag([0.0, 0.04 * 99.0]), R, above=3.0) == pytest.approx(np.sqrt(10.0))
    assert kernel_scale(np.diag([0.0, 0.04 * 9.0]), R, above=3.0) == pytest.approx(1.0)
    assert kernel_scale(np.diag([0.0, 0.04 * 4.0]), R, above=3.0) == 1.0


@pytest.mark.parametrize("on", [True, False], ids=["kernel-in-innovation-sigmas", "kernel-in-fix-sigmas"])
def test_a_drifted_smoother_keeps_the_right_fixes(run, on):
    """Right fixes only, the hold off: the smoother 6.3 m off (3 m sigma) takes them with the
    kernel in the innovation's sigmas, and retracts every one in the fix's alone."""
    fixes, wrong = _fixes(run)
    right = [f for f in fixes if f.t_meas not in wrong]
    cfg = SmootherConfig(fixes=FixConfig(kernel_on_innovation=on))
    out = drive(Isam2Smoother(_started_off(run), cfg), run.measurements, right, hold=FixHoldConfig(beyond_m=0.0))
    if on:
        assert all(o.accepted for o in out.outcomes), [o.reason for o in out.outcomes]
        assert _final_error(run, out) < 0.5
    else:
        assert all(o.reason.startswith("retracted") for o in out.outcomes), [o.reason for o in out.outcomes]
        assert _final_error(run, out) > 5.0


def test_agreement_ignores_the_correlation_factor_a_fix_was_widened_by(run):
    """The same fixes, each widened 50x for fusion beside the others it shares errors with (a long
    route's crater fixes reach 100x): judged alone, a wrong one still agrees with no right one."""
    fixes, wrong = _fixes(run)
    wide = [dataclasses.replace(f, cov_xyyaw=50.0 * f.cov_xyyaw, correlation_scale=50.0) for f in fixes]
    be = FarFixHold(EkfSlam(_started_off(run)), FixHoldConfig())
    out = drive(be, run.measurements, wide, hold=FixHoldConfig(beyond_m=0.0))
    assert not any(o.accepted for o in out.outcomes if o.fix.t_meas in wrong)
    assert be.stats().extra["fix_hold"]["released"] >= 1

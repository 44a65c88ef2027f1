"""Late fixes: roll back, apply at t_meas, replay; identical to the same fix delivered on time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.motion import split_step
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.geometry import yaw_of
from reloc.measurements import GlobalFix

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))


@pytest.fixture(scope="module")
def run():
    return simulate(7, duration_s=20.0, n_rocks=120)


def make_fix(run, k, t_meas=None, t_recv=None, offset_m=(0.08, -0.05)):
    t_meas = run.t[k] if t_meas is None else t_meas
    return GlobalFix(
        t_meas=t_meas, t_recv=t_recv if t_recv is not None else t_meas,
        x_m=run.truth_p[k, 0] + offset_m[0], y_m=run.truth_p[k, 1] + offset_m[1],
        yaw_rad=yaw_of(run.truth_R[k]) + 0.01, cov_xyyaw=np.diag([0.1**2, 0.1**2, 0.02**2]))


def feed(ekf, run, fixes_at=None, split_at=None):
    """Feed the run; ``fixes_at``: {step index: [fix, ...]} applied on time after that step (and its
    frame); ``split_at``: (step index, t) splits that step and applies ``fixes_at[k]`` between."""
    outcomes = []
    fixes_at = fixes_at or {}
    for k, step in enumerate(run.steps):
        if split_at is not None and k == split_at[0]:
            a, b = split_step(step, split_at[1])
            ekf.predict(a)
            outcomes += [ekf.apply_fix(f) for f in fixes_at.get(k, [])]
            ekf.predict(b)
        else:
            ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
        if split_at is None or k != split_at[0]:
            outcomes += [ekf.apply_fix(f) for f in fixes_at.get(k, [])]
    return outcomes


def assert_same(a: EkfSlam, b: EkfSlam, tol=1e-9):
    ea, eb = a.estimate(), b.estimate()
    assert ea.t == eb.t
    assert np.allclose(ea.T_world_base, eb.T_world_base, atol=tol, rtol=0)
    assert np.allclose(a.full_covariance(), b.full_covariance(), atol=tol, rtol=0)
    ma, mb = a.landmark_map("rocks"), b.landmark_map("rocks")
    assert np.array_equal(ma.ids, mb.ids)
    assert np.allclose(ma.xyz_world_m, mb.xyz_world_m, atol=tol, rtol=0)
    ta, tb = a.trajectory(), b.trajectory()
    assert np.array_equal(ta.t, tb.t)
    assert np.allclose(ta.T_world_base, tb.T_world_base, atol=tol, rtol=0)
    assert np.allclose(ta.cov, tb.cov, atol=tol, rtol=0)


def test_late_fix_equals_on_time(run):
    k = 250  # fix stamped at the end of step 249 (t = 8.33 s), delivered at the end of the run
    fix = make_fix(run, k)
    on_time = EkfSlam(START)
    (out_on,) = feed(on_time, run, {k - 1: [fix]})
    late = EkfSlam(START)
    feed(late, run)
    out_late = late.apply_fix(dataclasses.replace(fix, t_recv=run.t[-1]))
    assert out_on.accepted and out_late.accepted, (out_on, out_late)
    assert out_late.mahalanobis_d2 == pytest.approx(out_on.mahalanobis_d2, abs=1e-9)
    assert_same(on_time, late)
    assert late.stats().extra["n_late_fixes"] == 1
    # the fix moved the whole trajectory after t_meas
    moved = np.abs(late.trajectory().positions_m[-1] - EkfSlam_plain(run).trajectory().positions_m[-1])
    assert moved.max() > 1e-3


def EkfSlam_plain(run):
    ekf = EkfSlam(START)
    feed(ekf, run)
    return ekf


def test_late_fix_between_imu_samples_equals_on_time(run):
    k = 400
    t_meas = run.t[k] + 0.4 * (run.t[k + 1] - run.t[k])  # inside step k
    fix = make_fix(run, k, t_meas=t_meas)
    on_time = EkfSlam(START)
    feed(on_time, run, {k: [fix]}, split_at=(k, t_meas))
    late = EkfSlam(START)
    feed(late, run)
    assert late.apply_fix(dataclasses.replace(fix, t_recv=run.t[-1])).accepted
    assert_same(on_time, late)


def test_two_late_fixes_in_reverse_order_equal_on_time(run):
    fa, fb = make_fix(run, 200), make_fix(run, 450, offset_m=(-0.1, 0.15))
    on_time = EkfSlam(START)
    assert all(o.accepted for o in feed(on_time, run, {199: [fa], 449: [fb]}))
    late = EkfSlam(START)
    feed(late, run)
    assert late.apply_fix(dataclasses.replace(fb, t_recv=run.t[-1])).accepted
    assert late.apply_fix(dataclasses.replace(fa, t_recv=run.t[-1])).accepted
    assert_same(on_time, late)


def test_fix_older_than_history_is_rejected_and_state_untouched(run):
    cfg = EkfConfig(history_s=5.0)
    ekf = EkfSlam(START, cfg)
    feed(ekf, run)
    before = ekf.full_covariance(), ekf.estimate().T_world_base, len(ekf.trajectory())
    out = ekf.apply_fix(make_fix(run, 100, t_recv=run.t[-1]))  # 16.7 s old
    assert not out.accepted and out.reason.startswith("older than history")
    assert np.array_equal(before[0], ekf.full_covariance())
    assert np.array_equal(before[1], ekf.estimate().T_world_base)
    assert ekf.stats().n_fixes_rejected == 1
    assert ekf.stats().extra["fix_reject_reasons"] == {"older": 1}
    # within the history it is accepted
    assert ekf.apply_fix(make_fix(run, 500, t_recv=run.t[-1])).accepted


def test_rejected_late_fix_restores_everything(run):
    ekf = EkfSlam(START)
    feed(ekf, run)
    ref = EkfSlam_plain(run)
    out = ekf.apply_fix(make_fix(run, 300, t_recv=run.t[-1], offset_m=(10.0, 0.0)))
    assert not out.accepted and out.reason.startswith("distance gate")
    assert_same(ekf, ref, tol=0.0)
    # and the filter keeps working afterwards
    assert ekf.apply_fix(make_fix(run, 300, t_recv=run.t[-1])).accepted


def _offset_start(run, dx_m: float) -> PoseEstimate:
    T = np.eye(4)
    T[:3, :3] = run.truth_R[0]
    T[:3, 3] = run.truth_p[0] + np.array([dx_m, 0.0, 0.0])
    return PoseEstimate(run.t[0], T, np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))


def _feed_truth_fixes(ekf, run, every: int, delay_steps: int):
    """Feed the run with a truth fix every ``every`` steps, delivered ``delay_steps`` late."""
    outcomes, pending = [], []
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
        if k % every == 0 and k > 0:
            pending.append((k + delay_steps, make_fix(run, k + 1, offset_m=(0.0, 0.0))))
        while pending and pending[0][0] <= k:
            outcomes.append(ekf.apply_fix(pending.pop(0)[1]))
    return outcomes


@pytest.mark.parametrize("correlation_model", ["producer", "bias"])
def test_consistent_rejected_fixes_reopen_an_overconfident_filter(run, correlation_model):
    """Started 1.5 m off with a 1 cm sigma, the filter rejects the first fixes at the Mahalanobis
    gate; once three of them agree it inflates its pose covariance (with the fixes' shared offset
    a state, the offset's too) and follows them. With the recovery disabled it stays wrong."""
    fixes_every, delay = 30, 15
    gate = dataclasses.replace(EkfConfig().fix_gate, correlation_model=correlation_model)
    on = EkfSlam(_offset_start(run, 1.5), dataclasses.replace(EkfConfig(), fix_gate=gate))
    out_on = _feed_truth_fixes(on, run, fixes_every, delay)
    off_cfg = dataclasses.replace(EkfConfig(), fix_gate=dataclasses.replace(gate, consensus_n=0))
    off = EkfSlam(_offset_start(run, 1.5), off_cfg)
    out_off = _feed_truth_fixes(off, run, fixes_every, delay)
    assert not any(o.accepted for o in out_off)
    assert [o.accepted for o in out_on[:2]] == [False, False] and out_on[2].accepted
    assert on.stats().extra["n_consensus_resets"] >= 1
    err_on = np.linalg.norm(on.estimate().position_m[:2] - run.truth_p[-1, :2])
    err_off = np.linalg.norm(off.estimate().position_m[:2] - run.truth_p[-1, :2])
    assert err_off > 1.3
    assert err_on < 0.2


def test_inconsistent_rejected_fixes_do_not_reopen_the_filter(run):
    """Fixes that are far from the estimate but disagree with each other (alternating 1.5 m east
    and west) never complete a consensus: all stay rejected."""
    ekf = EkfSlam(START)
    outcomes = []
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
        if k % 30 == 0 and k > 0:
            sign = 1.0 if (k // 30) % 2 else -1.0
            outcomes.append(ekf.apply_fix(make_fix(run, k + 1, offset_m=(sign * 1.5, 0.0))))
    assert outcomes and not any(o.accepted for o in outcomes)
    assert ekf.stats().extra["n_consensus_resets"] == 0


def test_expected_fix_replays_from_its_own_time_with_the_same_result(run):
    k = 250  # t_meas at the end of step 249, away from the 2 s periodic checkpoints
    fix = dataclasses.replace(make_fix(run, k), t_recv=run.t[-1])
    plain, hinted = EkfSlam(START), EkfSlam(START)
    feed(plain, run)
    for j, step in enumerate(run.steps):
        if j == k:  # every input up to t_meas is in: the runner says a fix for t_meas may come
            hinted.expect_fix(fix.t_meas)
        hinted.predict(step)
        if j in run.frames:
            hinted.observe(run.frames[j])
    hinted.expect_fix(fix.t_meas - 1.0)  # a time already passed: ignored
    out_plain, out_hinted = plain.apply_fix(fix), hinted.apply_fix(fix)
    assert out_plain.accepted and out_hinted.accepted
    assert out_hinted.mahalanobis_d2 == pytest.approx(out_plain.mahalanobis_d2, abs=1e-9)
    assert_same(plain, hinted)
    n_plain = plain.stats().extra["n_replayed_entries"]
    n_hinted = hinted.stats().extra["n_replayed_entries"]
    assert n_hinted == len(run.steps) - k + sum(j >= k for j in run.frames)  # only what followed t_meas
    assert n_hinted < n_plain


def _fix_gate(**kw) -> EkfConfig:
    return EkfConfig(fix_gate=dataclasses.replace(EkfConfig().fix_gate, **kw))


def test_the_distance_model_counts_a_repeated_fix_once_per_source_and_replays_the_same(run):
    """fix_gate.correlation_model "distance": the same fix again at the same place is worth
    ~1/200 of the first (its match covariance re-scaled); a fix from another source is independent;
    late fixes applied in reverse order give the filter of the fixes on time."""
    distance = _fix_gate(correlation_model="distance", correlation_length_m=2.5)
    fix = dataclasses.replace(make_fix(run, 300, offset_m=(0.01, -0.01)), cov_xyyaw=np.diag([0.01**2, 0.01**2, 0.002**2]))
    other = dataclasses.replace(fix, source="craters")
    P = {}
    for name, cfg, fixes in [("once", distance, [fix]), ("twice", distance, [fix, fix]),
                             ("twice_producer", EkfConfig(), [fix, fix]), ("two_sources", distance, [fix, other]),
                             ("two_sources_producer", EkfConfig(), [fix, other])]:
        ekf = EkfSlam(START, cfg)
        assert all(o.accepted for o in feed(ekf, run, {299: fixes}))
        traj = ekf.trajectory()
        P[name] = traj.cov[np.searchsorted(traj.t, fix.t_meas), :2, :2].trace()  # just after the fixes
    assert P["twice"] == pytest.approx(P["once"], rel=0.02)  # the second adds ~1/200 of the information
    assert P["twice_producer"] < 0.7 * P["once"]  # taken as independent: about half the variance
    assert P["two_sources"] == pytest.approx(P["two_sources_producer"], rel=1e-12)
    fa, fb = make_fix(run, 200), make_fix(run, 450, offset_m=(-0.1, 0.15))
    on_time = EkfSlam(START, distance)
    assert all(o.accepted for o in feed(on_time, run, {199: [fa], 449: [fb]}))
    late = EkfSlam(START, distance)
    feed(late, run)
    assert late.apply_fix(dataclasses.replace(fb, t_recv=run.t[-1])).accepted
    assert late.apply_fix(dataclasses.replace(fa, t_recv=run.t[-1])).accepted
    assert_same(on_time, late)

"""Behaviour of the iSAM2 smoother on seeded synthetic runs: batch equivalence, late fixes,
retraction of wrong fixes, the fixed-lag window, recovery from failed updates, consistency."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from fgslam.smoother import Factorization, Isam2Smoother, SmootherConfig
from fgslam.smoother.config import FixConfig
from fgslam.smoother.solver import SolverUpdateError
from fgslam.smoother.synthetic import (
    SyntheticConfig,
    ate_m,
    drive,
    simulate_synthetic,
    synthetic_fixes,
)
from reloc.backend import Backend
from reloc.measurements import GlobalFix


@pytest.fixture(scope="module")
def short_run():
    return simulate_synthetic(SyntheticConfig(seed=11, duration_s=60.0))


def _fix_at(run, t: float, t_recv: float, offset_xy=(0.0, 0.0), sigma_m: float = 0.3) -> GlobalFix:
    T = run.gt_at(t)
    return GlobalFix(
        t, t_recv, T[0, 3] + offset_xy[0], T[1, 3] + offset_xy[1], float(np.arctan2(T[1, 0], T[0, 0])),
        np.diag([sigma_m**2, sigma_m**2, 0.02**2]),
    )


def _all_estimates(sm: Isam2Smoother) -> dict[int, np.ndarray]:
    out = {}
    for i in range(len(sm.kfs)):
        out[X(i)] = sm.solver.pose(X(i))
    for rec in sm.kinds.get("rocks").store.mapped():
        out[L(rec.lid)] = sm.solver.point(L(rec.lid))
    return out


def test_implements_backend_protocol(short_run):
    sm = Isam2Smoother(short_run.initial_pose)
    assert isinstance(sm, Backend)
    assert sm.name == "isam2"


def test_incremental_estimate_equals_batch_levenberg_marquardt(short_run):
    cfg = SmootherConfig(relinearize_threshold=0.0, relinearize_skip=1)
    fixes = [f for f, _ in synthetic_fixes(short_run, np.random.default_rng(1), period_s=9.0, delay_s=(1, 10))]
    sm = Isam2Smoother(short_run.initial_pose, cfg)
    drive(sm, short_run.measurements, fixes)
    assert sm.stats().n_fixes_accepted >= 3 and len(sm.kinds.get("rocks").store.mapped()) > 10
    sm.solver.extra_iterations(5)
    graph = gtsam.NonlinearFactorGraph()
    factors = sm.solver.factors()
    for i in range(factors.size()):
        if factors.at(i) is not None:
            graph.add(factors.at(i))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(100)
    batch = gtsam.LevenbergMarquardtOptimizer(graph, sm.solver.theta(), params).optimize()
    inc = _all_estimates(sm)
    worst = 0.0
    for key, v in inc.items():
        b = batch.atPose3(key).matrix() if gtsam.Symbol(key).chr() == ord("x") else batch.atPoint3(key)
        worst = max(worst, float(np.abs(np.asarray(b) - v).max()))
    assert worst < 1e-6


def test_late_fix_lands_where_an_on_time_fix_would(short_run):
    cfg = SmootherConfig(relinearize_threshold=0.0, relinearize_skip=1)
    t_meas = [20.3, 41.7]
    results = []
    for delay in (0.02, 15.0):  # on time: as soon as the odometry has reached t_meas
        sm = Isam2Smoother(short_run.initial_pose, cfg)
        fixes = [_fix_at(short_run, t, t + delay, offset_xy=(0.2, -0.1)) for t in t_meas]
        out = drive(sm, short_run.measurements, fixes)
        assert all(o.accepted for o in out.outcomes), [o.reason for o in out.outcomes]
        sm.solver.extra_iterations(5)
        results.append(sm.trajectory())
    np.testing.assert_allclose(results[0].positions_m, results[1].positions_m, atol=1e-6)
    np.testing.assert_allclose(results[0].T_world_base, results[1].T_world_base, atol=1e-6)


def test_estimate_between_keyframes_composes_odometry(short_run):
    from reloc.odometry import OdometryAssembler

    sm = Isam2Smoother(short_run.initial_pose)
    asm = OdometryAssembler()
    traces, n_kf = [], []
    for m in short_run.measurements:
        if m.t > 5.0:
            break
        if type(m).__name__ in ("CmdVel", "ImuSample"):
            step = asm.push(m)
            if step is not None:
                sm.predict(step)
                e = sm.estimate()
                assert e.t == pytest.approx(step.t1)
                assert np.linalg.eigvalsh(e.cov)[0] > 0
                traces.append(np.trace(e.cov[:3, :3]))
                n_kf.append(len(sm.kfs))
                err = np.linalg.norm(e.position_m - short_run.gt_at(e.t)[:3, 3])
                assert err < 0.05
    assert n_kf[-1] >= 4  # keyframes every interval_s = 1 s
    assert traces[-1] > traces[0]  # uncertainty grows with odometry only


def test_wrong_fix_passing_the_gate_is_retracted(short_run):
    cfg = SmootherConfig(fixes=FixConfig(gate_chi2=1e9, gate_distance_m=1e9))
    ref = Isam2Smoother(short_run.initial_pose, cfg)
    drive(ref, short_run.measurements, [])
    sm = Isam2Smoother(short_run.initial_pose, cfg)
    wrong = _fix_at(short_run, 30.0, 40.0, offset_xy=(6.0, 3.0))
    out = drive(sm, short_run.measurements, [wrong])
    assert not out.outcomes[0].accepted and out.outcomes[0].reason.startswith("retracted")
    retracted = sm.stats().extra["retracted_fixes"]
    assert len(retracted) == 1 and retracted[0]["t_meas"] == 30.0
    # after retraction the trajectory is the one without the fix
    d = np.abs(sm.trajectory().positions_m - ref.trajectory().positions_m).max()
    assert d < 0.02


def test_a_fix_with_a_height_is_retracted_against_its_own_4_dof_bound(short_run):
    """The same wrong fix with a height is held to retract_chi2_with_height (4 dof), without one
    to retract_chi2 (3 dof)."""
    import dataclasses

    from reloc.measurements import FixHeight

    wrong = _fix_at(short_run, 30.0, 40.0, offset_xy=(6.0, 3.0))
    z = float(short_run.gt_at(30.0)[2, 3])
    with_height = dataclasses.replace(wrong, height=FixHeight(z, 0.05**2, np.zeros(3)))
    for fix, planar_bound, height_bound, retracted in [
        (with_height, 1.0, 1e9, False), (with_height, 1e9, 1.0, True), (wrong, 1.0, 1e9, True), (wrong, 1e9, 1.0, False),
    ]:
        cfg = SmootherConfig(fixes=FixConfig(gate_chi2=1e9, gate_distance_m=1e9, height_gate_chi2=1e9,
                                             retract_chi2=planar_bound, retract_chi2_with_height=height_bound))
        sm = Isam2Smoother(short_run.initial_pose, cfg)
        out = drive(sm, short_run.measurements, [fix])
        assert out.outcomes[0].reason.startswith("retracted") == retracted, (fix.height, out.outcomes[0].reason)


def test_old_fixes_are_rejected_with_a_reason_and_fixed_lag_keeps_working(short_run):
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(fixes=FixConfig(max_age_s=20.0)))
    drive(sm, short_run.measurements[: len(short_run.measurements) * 3 // 4], [])
    t_now = sm.estimate().t
    assert t_now > 30.0
    o = sm.apply_fix(_fix_at(short_run, 5.0, t_now))
    assert not o.accepted and "history" in o.reason
    o = sm.apply_fix(_fix_at(short_run, t_now + 1.0, t_now + 1.0))
    assert not o.accepted and "ahead" in o.reason

    cfg = SmootherConfig(fixed_lag_s=12.0)
    lag = Isam2Smoother(short_run.initial_pose, cfg)
    fixes = [_fix_at(short_run, 10.0, 40.0), _fix_at(short_run, 35.0, 41.0, offset_xy=(0.1, 0.1))]
    out = drive(lag, short_run.measurements, fixes)
    assert not out.outcomes[0].accepted and "window" in out.outcomes[0].reason
    assert out.outcomes[1].accepted
    extra = lag.stats().extra
    assert extra["n_fixes_older_than_window"] == 1 and extra["fix_reject_reasons"] == {"outside": 1}
    n_alive_x = sum(1 for k in lag.solver._alive if gtsam.Symbol(k).chr() == ord("x"))
    assert n_alive_x <= 14  # ~lag / keyframe interval, not the 60 keyframes of the run
    tr = lag.trajectory()
    assert len(tr) == len(lag.kfs) and np.all(np.isfinite(tr.T_world_base))
    assert ate_m(short_run, tr.t, tr.T_world_base) < 0.3


def test_fixed_lag_marginalizes_in_batches_once_per_period(short_run):
    """With marginalize_every_s, poses leave the window in batches at most once per period and
    stay between fixed_lag_s and fixed_lag_s + the period old; the estimate is that of
    marginalizing at every keyframe."""
    lag_s, every = 10.0, 4.0
    runs = {}
    for e in (0.0, every):
        sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(fixed_lag_s=lag_s, marginalize_every_s=e))
        leave_times, ages = [], []
        update = sm.solver.update

        def spy(*a, _sm=sm, _update=update, **k):
            before = {key for key in _sm.solver._alive if gtsam.Symbol(key).chr() == ord("x")}
            out = _update(*a, **k)
            after = {key for key in _sm.solver._alive if gtsam.Symbol(key).chr() == ord("x")}
            t_now = _sm.kfs.t[-1]
            if before - after:
                leave_times.append(t_now)
            ages.extend(t_now - _sm.kfs.t[gtsam.Symbol(key).index()] for key in after)
            return out

        sm.solver.update = spy
        drive(sm, short_run.measurements, [])
        runs[e] = (sm, np.array(leave_times), np.array(ages))
    dt_kf = float(np.median(np.diff(runs[0.0][0].kfs.t)))
    for e, (_sm, leave, ages) in runs.items():
        assert len(leave) > 3
        assert ages.max() <= lag_s + e + dt_kf + 1e-6
        if e > 0:
            assert np.all(np.diff(leave) >= e - 1e-6)  # one batch per period, not one per keyframe
        else:
            assert np.median(np.diff(leave)) <= dt_kf + 1e-6
    a, b = (runs[e][0].trajectory() for e in (0.0, every))
    assert ate_m(short_run, a.t, a.T_world_base) < 0.3 and ate_m(short_run, b.t, b.T_world_base) < 0.3
    # the same estimate, unless a rock re-seen near the window's edge was associated otherwise
    # (it leaves up to one period earlier in batches; seed 11 makes 13 rocks instead of 12 on some
    # CPUs, and its track then differs by 0.13 m): the same rocks, the same poses within 5 cm
    diff = np.max(np.linalg.norm(a.T_world_base[:, :3, 3] - b.T_world_base[:, :3, 3], axis=1))
    same_rocks = runs[0.0][0].stats().n_landmarks == runs[every][0].stats().n_landmarks
    assert diff < (0.05 if same_rocks else 0.2)


def test_failed_updates_leave_the_solver_usable(short_run):
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig())
    drive(sm, short_run.measurements[: len(short_run.measurements) // 3], [])
    k = len(sm.kfs) - 1
    before = sm.solver.pose(X(k))
    # 1. invalid input is refused before it reaches GTSAM
    bad = gtsam.Values()
    bad.insert(L(99999), np.array([np.nan, 0.0, 0.0]))
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPoint3(L(99999), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    with pytest.raises(SolverUpdateError, match="not finite"):
        sm.solver.update(g, bad)
    g2 = gtsam.NonlinearFactorGraph()
    g2.add(gtsam.PriorFactorPose3(X(12345), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)))
    with pytest.raises(SolverUpdateError, match="not in the solver"):
        sm.solver.update(g2, gtsam.Values())
    # 2. an update GTSAM itself fails on (a point seen by a range only: indeterminant system)
    g3 = gtsam.NonlinearFactorGraph()
    g3.add(gtsam.RangeFactor3D(X(k), L(99998), 3.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.1)))
    v3 = gtsam.Values()
    v3.insert(L(99998), before[:3, 3] + np.array([3.0, 0.0, 0.0]))
    with pytest.raises(SolverUpdateError, match="in QR as well, and was rolled back"):
        sm.solver.update(g3, v3)
    # Cholesky failed, the batch was tried again in QR (truly indeterminate: failed there too)
    assert sm.solver.n_recoveries == 2 and sm.solver.n_qr_retries == 0
    assert sm.solver.factorization is Factorization.QR
    # same problem, rebuilt (and fully relinearized once): the estimate barely moves
    np.testing.assert_allclose(sm.solver.pose(X(k)), before, atol=5e-3)
    assert not sm.solver.alive(L(99998))
    # the smoother carries on: more keyframes, a fix
    out = drive(sm, short_run.measurements[len(short_run.measurements) // 3 :], [_fix_at(short_run, 40.0, 45.0)])
    assert len(sm.kfs) > k + 20 and out.outcomes[0].accepted
    tr = sm.trajectory()
    assert ate_m(short_run, tr.t, tr.T_world_base) < 0.3


def test_after_a_cholesky_failure_qr_for_a_spell_then_cholesky_and_fix_factors_keep_their_index(short_run):
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(cholesky_retry_updates=10))
    third = len(short_run.measurements) // 3
    out = drive(sm, short_run.measurements[:third], [_fix_at(short_run, 12.0, 14.0)])
    assert out.outcomes[0].accepted
    rec = sm.fixes[0]

    def fix_factor_keys():
        f = sm.solver.factors().at(rec.factor_index)
        return None if f is None else list(f.keys())

    assert fix_factor_keys() == [rec.key]
    k = len(sm.kfs) - 1
    g = gtsam.NonlinearFactorGraph()  # a point seen by a range only: an indeterminate system
    g.add(gtsam.RangeFactor3D(X(k), L(99998), 3.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.1)))
    v = gtsam.Values()
    v.insert(L(99998), sm.solver.pose(X(k))[:3, 3] + np.array([3.0, 0.0, 0.0]))
    with pytest.raises(SolverUpdateError):
        sm.solver.update(g, v)
    assert sm.solver.factorization is Factorization.QR
    assert fix_factor_keys() == [rec.key]  # the fix record follows its factor into the rebuilt solver
    drive(sm, short_run.measurements[third:], [])
    assert sm.solver.factorization is Factorization.CHOLESKY and sm.solver.n_cholesky_returns == 1
    assert sm.stats().extra["n_cholesky_returns"] == 1
    assert fix_factor_keys() == [rec.key]
    tr = sm.trajectory()
    assert ate_m(short_run, tr.t, tr.T_world_base) < 0.3


def test_a_cholesky_return_that_fails_keeps_qr_for_a_longer_spell(short_run):
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(cholesky_retry_updates=5))
    third = len(short_run.measurements) // 3
    drive(sm, short_run.measurements[:third], [])
    k = len(sm.kfs) - 1
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.RangeFactor3D(X(k), L(99998), 3.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.1)))
    v = gtsam.Values()
    v.insert(L(99998), sm.solver.pose(X(k))[:3, 3] + np.array([3.0, 0.0, 0.0]))
    with pytest.raises(SolverUpdateError):
        sm.solver.update(g, v)
    rebuild, calls = sm.solver._rebuild, []

    def failing_once(*a, **kw):  # the first return to Cholesky meets an indeterminate window
        calls.append(sm.solver.factorization)
        if len(calls) == 1:
            raise RuntimeError("Indeterminate linear system detected while working near variable")
        return rebuild(*a, **kw)

    sm.solver._rebuild = failing_once
    drive(sm, short_run.measurements[third:], [])
    assert calls[0] is Factorization.CHOLESKY and sm.solver._qr_spell == 10
    assert sm.solver.n_cholesky_returns == 1 and sm.solver.factorization is Factorization.CHOLESKY
    tr = sm.trajectory()
    assert ate_m(short_run, tr.t, tr.T_world_base) < 0.3


def test_a_rover_turning_in_place_far_from_any_fix_keeps_every_update():
    """Tens of metres of absolute sigma (a long drive without fixes) and a turn in place: the
    keyframes the turn starts are joined by sub-millimetre translations, a system GTSAM's Cholesky
    refuses as indeterminate; the batch goes in with QR, landmark factors and all, and the
    covariance keeps its size. Driving on, keyframes come every second."""
    from _synth_stream import make_stream

    from fgslam.runner import run_backend
    from reloc.backend import PoseEstimate

    inputs = make_stream(seed=3, duration_s=8.0, speed_mps=0.0)  # the S-curve's yaw rate, no speed
    cov = np.diag([30.0**2, 30.0**2, 1.0, 1e-4, 1e-4, 0.05**2])
    sm = Isam2Smoother(PoseEstimate(inputs.initial.t, inputs.initial.T_world_base, cov))
    run_backend(sm, inputs.measurements)
    assert sm.n_failed_updates == 0 and len(sm.kfs) >= 3
    assert sm.estimate().planar_sigma_m > 29.0
    moving = make_stream(seed=3, duration_s=8.0)
    sm = Isam2Smoother(PoseEstimate(moving.initial.t, moving.initial.T_world_base, cov))
    run_backend(sm, moving.measurements)
    assert sm.n_failed_updates == 0 and len(sm.kfs) >= 7


def test_a_batch_cholesky_calls_indeterminate_goes_in_with_qr_whole():
    """GTSAM's Cholesky "indeterminate" is a heuristic a well-posed batch can trip: the batch is
    tried again in QR, and the keyframe keeps its landmark factors (before, it went in without
    them). A batch that fails in QR as well is refused as before
    (test_failed_updates_leave_the_solver_usable)."""
    from _synth_stream import make_stream

    from fgslam.runner import run_backend

    inputs = make_stream(seed=3, duration_s=12.0)
    sm = Isam2Smoother(inputs.initial)
    solver = sm.solver
    calls = {"n": 0}
    apply = solver._apply

    def failing_once(graph, values, *args):
        calls["n"] += 1
        if calls["n"] == 6 and solver.factorization is Factorization.CHOLESKY:
            raise RuntimeError("Indeterminate linear system detected while working near variable")
        return apply(graph, values, *args)

    solver._apply = failing_once
    run_backend(sm, inputs.measurements)
    assert calls["n"] > 6
    assert solver.n_qr_retries == 1 and solver.n_recoveries == 1 and sm.n_failed_updates == 0
    assert solver.factorization is Factorization.QR  # for its spell
    rocks = sm.kinds.get("rocks")
    assert rocks.n_landmarks > 0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 5])
def test_consistency_nees_and_3sigma_envelope(seed):
    run = simulate_synthetic(SyntheticConfig(seed=seed, duration_s=240.0))
    fixes = [f for f, _ in synthetic_fixes(run, np.random.default_rng(seed))]
    sm = Isam2Smoother(run.initial_pose)
    out = drive(sm, run.measurements, fixes)
    tr = sm.trajectory()
    for t, Ts, Cs in ((tr.t, tr.T_world_base, tr.cov), (out.est_t, out.est_T, out.est_cov)):
        nees, inside = [], []
        for ti, T, C in zip(t, Ts, Cs):
            G = run.gt_at(ti)
            dR = G[:3, :3] @ T[:3, :3].T
            e = np.concatenate([G[:3, 3] - T[:3, 3], 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])])
            nees.append(e @ np.linalg.solve(C, e))
            inside.append(np.all(np.abs(e[:2]) <= 3.0 * np.sqrt(np.diag(C)[:2])))
        # chi2(6) has mean 6: an overconfident smoother would be far above, a timid one far below
        assert 1.0 < np.mean(nees) < 12.0, np.mean(nees)
        assert np.mean(inside) > 0.9


@pytest.mark.slow
def test_ten_percent_wrong_fixes_raise_ate_by_less_than_ten_percent():
    run = simulate_synthetic(SyntheticConfig(seed=7, duration_s=300.0, slip_sigma=0.1, gyro_bias_radps=5e-4))
    ates = {}
    for name, frac in (("good", 0.0), ("wrong", 0.1)):
        fx = synthetic_fixes(run, np.random.default_rng(3), wrong_fraction=frac)
        assert sum(w for _, w in fx) == (0 if frac == 0 else round(0.1 * len(fx)))
        sm = Isam2Smoother(run.initial_pose)
        drive(sm, run.measurements, [f for f, _ in fx])
        tr = sm.trajectory()
        ates[name] = ate_m(run, tr.t, tr.T_world_base)
    none = Isam2Smoother(run.initial_pose)
    drive(none, run.measurements, [])
    tr = none.trajectory()
    ates["none"] = ate_m(run, tr.t, tr.T_world_base)
    assert ates["good"] < ates["none"]  # fixes help on this drifting run
    assert ates["wrong"] < 1.10 * ates["good"], ates


def test_bad_initial_pose_is_refused_and_config_round_trips():
    from fgslam.errors import SmootherError
    from reloc.backend import PoseEstimate
    from reloc.config import config_from_dict, config_to_dict

    with pytest.raises(SmootherError, match="T_world_base"):
        Isam2Smoother(PoseEstimate(0.0, np.eye(3), np.eye(6)))
    with pytest.raises(SmootherError, match="finite"):
        Isam2Smoother(PoseEstimate(0.0, np.full((4, 4), np.nan), np.eye(6)))
    cfg = config_from_dict(SmootherConfig, {"fixed_lag_s": 30, "factorization": "qr", "fixes": {"cauchy_k": 3.0}})
    assert cfg.fixed_lag_s == 30.0 and cfg.factorization is Factorization.QR and cfg.fixes.cauchy_k == 3.0
    assert config_from_dict(SmootherConfig, config_to_dict(cfg)) == cfg


def test_cli_bench_isam2_writes_results(tmp_path):
    import json

    from fgslam.cli import main

    rc = main(["bench", "isam2", "--source", "synthetic", "--duration-s", "40", "--distance-m", "12",
               "--lag-s", "10", "--no-ekf", "--out", str(tmp_path)])
    assert rc == 0
    res = json.loads((tmp_path / "results.json").read_text())
    runs = {r["case"]: r for r in res["traverse"]["runs"]}
    assert set(runs) == {"no_fixes", "fixes", "fixes_10pct_wrong"}
    assert all(np.isfinite(r["ate_final_m"]) and r["latency_p99_ms"] > 0 for r in runs.values())
    assert res["fixed_lag"]["distance_m"] > 10 and len(res["fixed_lag"]["bins"]) == 10


def test_rock_cov_scale_equals_feeding_scaled_covariances():
    import dataclasses

    from fgslam.errors import SmootherError
    from fgslam.smoother.config import LandmarkConfig
    from reloc.measurements import RockObservations

    run = simulate_synthetic(SyntheticConfig(seed=5, duration_s=20.0))
    scaled_meas = [dataclasses.replace(m, cov_base_m2=m.cov_base_m2 * 4.0) if isinstance(m, RockObservations) else m
                   for m in run.measurements]
    cfg = SmootherConfig(landmarks=LandmarkConfig(rock_cov_scale=4.0))
    a, b, plain = Isam2Smoother(run.initial_pose, cfg), Isam2Smoother(run.initial_pose), Isam2Smoother(run.initial_pose)
    drive(a, run.measurements, [])
    drive(b, scaled_meas, [])
    drive(plain, run.measurements, [])
    np.testing.assert_allclose(a.estimate().T_world_base, b.estimate().T_world_base, atol=1e-9)
    np.testing.assert_allclose(a.estimate().cov, b.estimate().cov, rtol=1e-6, atol=1e-12)
    assert np.trace(a.estimate().cov[:2, :2]) > 1.1 * np.trace(plain.estimate().cov[:2, :2])
    with pytest.raises(SmootherError, match="rock_cov_scale"):
        LandmarkConfig(rock_cov_scale=0.0)


def test_calibration_variable_recovers_a_yaw_and_scale_error():
    import dataclasses

    from reloc.calibration import CalibrationConfig
    from reloc.geometry import exp_so3
    from reloc.measurements import RockObservations

    run = simulate_synthetic(SyntheticConfig(seed=4, duration_s=90.0))
    E, scale = exp_so3(np.radians([0.0, 0.0, 1.5])), 1.01
    meas = [dataclasses.replace(m, xyz_base_m=scale * m.xyz_base_m @ E.T,
                                cov_base_m2=scale**2 * np.einsum("ij,njk,lk->nil", E, m.cov_base_m2, E))
            if isinstance(m, RockObservations) else m for m in run.measurements]
    cal = CalibrationConfig(yaw_sigma_deg=3.0, scale_sigma=0.03)
    sm = Isam2Smoother(run.initial_pose, SmootherConfig(calibration=cal))
    drive(sm, meas, [])
    c = sm.stats().extra["calibration"]
    assert abs(c["rotation_deg"][2] - 1.5) < 3 * c["rotation_sigma_deg"][2] and c["rotation_sigma_deg"][2] < 1.0
    assert abs(c["scale"] - scale) < 3 * c["scale_sigma"]
    assert c["rotation_deg"][:2] == [0.0, 0.0]  # roll and pitch not estimated (sigma 0)
    plain = Isam2Smoother(run.initial_pose)
    drive(plain, meas, [])
    ta, tp = sm.trajectory(), plain.trajectory()
    assert ate_m(run, ta.t, ta.T_world_base) < ate_m(run, tp.t, tp.T_world_base)
    # fixed-lag: C(0) is re-stamped at every keyframe, so it stays in the window and is estimated
    lag = Isam2Smoother(run.initial_pose, SmootherConfig(calibration=cal, fixed_lag_s=20.0))
    drive(lag, meas, [])
    assert lag.solver.alive(gtsam.symbol("c", 0)) and len(lag.kfs) > 40
    c = lag.stats().extra["calibration"]
    assert abs(c["rotation_deg"][2] - 1.5) < 3 * c["rotation_sigma_deg"][2] and c["rotation_sigma_deg"][2] < 1.0
    assert abs(c["scale"] - scale) < 3 * c["scale_sigma"]


def _pitched_run():
    """The synthetic drive (seed 4, 90 s) with a 1 deg mounting pitch tilting every rock, and the
    height error of a smoother on it: RMS, |final|, final sigma."""
    import dataclasses

    from reloc.geometry import exp_so3
    from reloc.measurements import RockObservations

    run = simulate_synthetic(SyntheticConfig(seed=4, duration_s=90.0))
    E = exp_so3(np.radians([0.0, 1.0, 0.0]))
    meas = [dataclasses.replace(m, xyz_base_m=m.xyz_base_m @ E.T,
                                cov_base_m2=np.einsum("ij,njk,lk->nil", E, m.cov_base_m2, E))
            if isinstance(m, RockObservations) else m for m in run.measurements]

    def height_error(sm):
        tr = sm.trajectory()
        gt_z = np.array([run.gt_at(t)[2, 3] for t in tr.t])
        e = tr.T_world_base[:, 2, 3] - gt_z
        return float(np.sqrt(np.mean(e**2))), abs(float(e[-1])), float(np.sqrt(sm.estimate().cov[2, 2]))

    return run, meas, height_error


def test_calibration_variable_recovers_a_mounting_pitch_and_holds_the_height():
    """A 1 deg mounting pitch tilts every rock: without the pitch in C(0) the landmarks pull the
    rover's height off (the odometry on gravity says level) and its sigma does not cover it; with
    it, the pitch is recovered within 3 sigma and the height error sits inside 3 sigma (the bound
    the run without it breaks), with a smaller RMS."""
    from reloc.calibration import CalibrationConfig

    run, meas, height_error = _pitched_run()
    plain = Isam2Smoother(run.initial_pose)
    drive(plain, meas, [])
    rms_plain, end_plain, sigma_plain = height_error(plain)
    assert end_plain > 3 * sigma_plain  # overconfident in a height the mounting pitch pulls off
    sm = Isam2Smoother(run.initial_pose, SmootherConfig(calibration=CalibrationConfig(roll_pitch_sigma_deg=2.0)))
    drive(sm, meas, [])
    c = sm.stats().extra["calibration"]
    assert abs(c["rotation_deg"][1] - 1.0) < 3 * c["rotation_sigma_deg"][1] and c["rotation_sigma_deg"][1] < 0.6
    assert abs(c["rotation_deg"][0]) < 3 * c["rotation_sigma_deg"][0] and c["rotation_deg"][2] == 0.0
    rms, end, sigma = height_error(sm)
    # One draw of the final error, and a run whose relinearizations follow the last bits of the
    # arithmetic: the same code and packages gave end 0.6 sigma, RMS 0.016 m against 0.124 on one
    # machine (2026-12-03) and 1.17 sigma, RMS 0.067 m against 0.122 (pitch 1.53 +- 0.43 deg) on an
    # AMD EPYC (2026-12-04). 1 sigma is no bound; 3 sigma is the consistency check.
    assert end < 3 * sigma and rms < 0.7 * rms_plain, (end, sigma, rms, rms_plain)


def test_a_held_roll_stays_nominal_while_the_pitch_is_recovered():
    """``calibration.roll_sigma_deg: 0`` beside a pitch sigma: C(0)'s roll (and yaw) stay at 0,
    the 1 deg mounting pitch is recovered within 3 sigma and the height error sits inside 3 sigma."""
    from reloc.calibration import CalibrationConfig

    cal = CalibrationConfig(roll_pitch_sigma_deg=2.0, roll_sigma_deg=0.0)
    assert cal.enabled and np.degrees(cal.prior_sigmas()[:3]) == pytest.approx([0.0, 2.0, 0.0])
    run, meas, height_error = _pitched_run()
    sm = Isam2Smoother(run.initial_pose, SmootherConfig(calibration=cal))
    drive(sm, meas, [])
    c = sm.stats().extra["calibration"]
    assert abs(c["rotation_deg"][1] - 1.0) < 3 * c["rotation_sigma_deg"][1] and c["rotation_sigma_deg"][1] < 0.6
    assert abs(c["rotation_deg"][0]) < 1e-3 and c["rotation_sigma_deg"][0] < 1e-3  # held by the stiff prior
    rms, end, sigma = height_error(sm)
    assert end < 3 * sigma, (end, sigma, rms)


def test_after_a_late_fix_the_cached_newest_marginal_is_exact(short_run):
    """A fix update puts the two newest keyframes last in the elimination: the cached marginal of
    the newest one equals the batch marginal (to 2 %: iSAM2 linearizes where it last relinearized,
    the batch at the current estimate) and the joint marginal of the two."""
    sm = Isam2Smoother(short_run.initial_pose)
    drive(sm, [m for m in short_run.measurements if m.t < 40.0], [])
    k = len(sm.kfs) - 1
    out = sm.apply_fix(_fix_at(short_run, sm.kfs.t[k - 2] + 0.1, sm.kfs.t[k], offset_xy=(0.05, 0.0)))
    assert out.accepted
    batch = sm.solver.marginal_covs([X(k)])[0]
    assert np.allclose(sm.cov_kf, batch, rtol=0.02, atol=0.02 * np.sqrt(np.outer(np.diag(batch), np.diag(batch))).max())
    joint = sm.solver.isam.jointMarginalCovariance([X(k - 1), X(k)])
    assert np.allclose(joint.at(X(k), X(k)), sm.cov_kf, rtol=1e-6, atol=1e-12)


def test_fixes_on_the_newest_and_older_keyframes_all_update(short_run):
    """Fixes on the newest keyframe (only the root re-eliminated) and on older ones, one after
    the other: every one is applied (none fails in the solver's ordering)."""
    sm = Isam2Smoother(short_run.initial_pose)
    ms = short_run.measurements
    t_prev = -np.inf
    for t_end in (12.0, 20.0, 28.0, 36.0, 44.0, 52.0):
        drive(sm, [m for m in ms if t_prev <= m.t < t_end], [])
        t_prev = t_end
        k = len(sm.kfs) - 1
        for t_meas in (sm.acc.t_now, sm.kfs.t[k] + 0.05, sm.kfs.t[max(k - 3, 0)] + 0.05):
            out = sm.apply_fix(_fix_at(short_run, t_meas, sm.acc.t_now, sigma_m=0.2))
            assert out.accepted, out.reason
    assert sm.stats().extra["n_failed_updates"] == 0


def test_consider_mode_has_no_calibration_variable_and_only_cpp_rock_factors(short_run):
    """calibration_mode "consider": no C(0) in the solver, every rock factor a C++ one."""
    from reloc.calibration import CalibrationConfig

    cal = CalibrationConfig(yaw_sigma_deg=0.15, scale_sigma=0.003)
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(calibration=cal, calibration_mode="consider"))
    drive(sm, short_run.measurements[:3000], [])
    graph = sm.solver.factors()
    kinds = {type(graph.at(i)).__name__ for i in range(graph.size()) if graph.at(i) is not None}
    assert "CustomFactor" not in kinds and "BearingRangeFactor3D" in kinds
    assert not sm.solver.alive(gtsam.symbol("c", 0)) and sm.calibration() == {}


def test_a_marginalizing_keyframe_takes_its_predicted_covariance_an_upper_bound(short_run):
    """Fixed-lag: after an update that marginalized keys, the newest keyframe's covariance is its
    prediction from the previous keyframe, never below its marginal; other updates keep the marginal."""
    sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(fixed_lag_s=10.0, marginalize_every_s=4.0))
    seen = []
    refresh = sm._refresh_latest

    def spy(cov=None):
        refresh(cov)
        k = len(sm.kfs) - 1
        seen.append((cov is not None, sm.cov_kf.copy(), sm.solver.marginal_cov(X(k))))

    sm._refresh_latest = spy
    drive(sm, short_run.measurements, [])
    predicted = [(c, m) for p, c, m in seen if p]
    assert 5 <= len(predicted) <= len(seen) / 3
    for c, m in predicted:
        # an upper bound (to the relinearization between the two: 1e-3 of the marginal's scale)
        assert np.linalg.eigvalsh(c - m).min() > -1e-3 * np.linalg.eigvalsh(m).max()
        assert np.trace(c) < 3.0 * np.trace(m)  # and a close one (one keyframe's odometry)
    assert all(np.allclose(c, m) for p, c, m in seen if not p)


def test_the_landmark_map_covariance_holds_the_drift():
    """The map given to the relocalizer is in the world: its covariance holds the drift of the poses
    that placed each landmark (the records' own covariance is relative to the map around them,
    and against the truth it is ~100x optimistic on this drifting run)."""
    from scipy.spatial import cKDTree

    run = simulate_synthetic(SyntheticConfig(seed=11, duration_s=120.0))
    sm = Isam2Smoother(run.initial_pose)
    drive(sm, run.measurements, [])
    tree = cKDTree(run.rocks_world_m)

    def nees(m):
        _, j = tree.query(m.xyz_world_m)
        e = m.xyz_world_m[:, :2] - run.rocks_world_m[j, :2]
        return float(np.mean(np.einsum("ki,kij,kj->k", e, np.linalg.inv(m.cov_world_m2[:, :2, :2]), e)))

    world = sm.landmark_map("rocks")
    assert len(world) > 15 and 0.3 < nees(world) < 5.0  # 2 dof
    assert nees(sm.kinds.named("rocks").landmark_map()) > 50.0


def test_fixed_lag_translation_threshold_spares_batch_steps_and_keeps_the_estimate():
    """A fix moves the whole fixed-lag window; relinearizing translations only beyond
    ``fixed_lag_translation_threshold_m`` (0.1 m) spares iSAM2 batch steps and keeps the estimate
    within its bound (seeded synthetic, fixes of 0.1 m sigma every 5 s: 25 -> 16 batch steps,
    final ATE 0.042 -> 0.061 m; on rocky-1km it was 42 -> 5 and 0.074 -> 0.069 m)."""
    run = simulate_synthetic(SyntheticConfig(seed=11, duration_s=120.0))
    fixes = [f for f, _ in synthetic_fixes(run, np.random.default_rng(2), period_s=5.0, delay_s=(1, 4), sigma_xy_m=0.1)]
    out = {}
    for th in (0.0, 0.1):
        sm = Isam2Smoother(run.initial_pose, SmootherConfig(fixed_lag_s=30.0, fixed_lag_translation_threshold_m=th))
        n_batch = [0]
        update = sm.solver.update

        def spy(*a, _sm=sm, _update=update, _n=n_batch, **k):
            res = _update(*a, **k)
            _n[0] += bool(_sm.solver.ifls.getISAM2Result().getBatchReorderTriggered())
            return res

        sm.solver.update = spy
        res = drive(sm, run.measurements, fixes)
        tr = sm.trajectory()
        out[th] = (n_batch[0], sum(o.accepted for o in res.outcomes), ate_m(run, tr.t, tr.T_world_base))
    assert out[0.1][0] < 0.8 * out[0.0][0]
    assert out[0.1][1] == out[0.0][1] == len(fixes)
    assert out[0.1][2] < 0.1


def test_fixed_lag_compaction_bounds_the_factor_slots_and_keeps_the_estimate_and_the_fixes(short_run):
    """compact_after_slots: GTSAM keeps a slot for every factor ever added; the fixed-lag solver
    is rebuilt from its live factors when they pile up, so the slots stay bounded, the estimate
    is that of the solver never compacted, and an accepted fix's record follows its factor."""
    fixes = [_fix_at(short_run, 20.0, 22.0), _fix_at(short_run, 54.0, 56.0, offset_xy=(0.05, -0.05))]
    runs, slots = {}, {}
    for every in (0, 100):
        sm = Isam2Smoother(short_run.initial_pose, SmootherConfig(fixed_lag_s=12.0, compact_after_slots=every))
        seen = []
        update = sm.solver.update

        def spy(*a, _sm=sm, _update=update, _seen=seen, **k):
            out = _update(*a, **k)
            _seen.append(_sm.solver.factors().size())
            return out

        sm.solver.update = spy
        out = drive(sm, short_run.measurements, fixes)
        assert all(o.accepted for o in out.outcomes)
        runs[every], slots[every] = sm, np.array(seen)
    lazy, compact = runs[0], runs[100]
    assert lazy.solver.n_compactions == 0 and compact.solver.n_compactions >= 2
    assert compact.stats().extra["n_compactions"] == compact.solver.n_compactions
    assert slots[0][-1] > 300  # without it the slots only grow
    live = compact.solver.factors().nrFactors()
    assert slots[100].max() <= max(100, 2 * live) + 50  # one update's worth above the bound
    for rec in compact.fixes:  # the fix records point at their factors in the rebuilt solver
        if compact.solver.alive(rec.key):
            assert list(compact.solver.factors().at(rec.factor_index).keys()) == [rec.key]
        else:  # marginalized with its keyframe: no index that now belongs to another factor
            assert rec.factor_index == -1
    assert any(compact.solver.alive(r.key) for r in compact.fixes)
    a, b = lazy.trajectory(), compact.trajectory()
    assert np.abs(a.positions_m - b.positions_m).max() < 0.01
    assert ate_m(short_run, b.t, b.T_world_base) < 0.3

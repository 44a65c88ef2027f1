"""The fixes' shared error as variables of the smoother (``FixConfig.correlation_model`` "bias",
:mod:`fgslam.smoother.fix_offsets`): consistent where fixes taken as independent are not, the
offset chain's bookkeeping (a new variable per fix, reuse, a fresh start, the fixed-lag window),
and a wrong fix still retracted."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.config import FixConfig, OdometryNoiseConfig
from fgslam.smoother.factors import make_fix_factor, make_gauss_markov_factor
from fgslam.smoother.kinds import OFFSET_SYMBOL, symbol_of
from fgslam.smoother.synthetic import SyntheticConfig, drive, simulate_synthetic
from reloc.backend import PoseEstimate
from reloc.errors import MeasurementError
from reloc.geometry import yaw_of
from reloc.kinds import KindLayerError, LandmarkKind
from reloc.measurements import FixHeight, GlobalFix, RockObservations

L_M, SHARE = 1.0, 0.9  # correlation length of the shared error (m of path), its share of the fix's variance
C_FIX = np.diag([0.05**2, 0.05**2, 0.01**2])
START_COV = np.diag([0.3**2, 0.3**2, 0.01**2, 1e-4, 1e-4, 0.05**2])
EVERY_S = 0.5


@pytest.fixture(scope="module")
def run():
    """30 s of odometry without rocks: the fixes' errors are what the position error is made of."""
    r = simulate_synthetic(SyntheticConfig(seed=3, duration_s=30.0))
    return dataclasses.replace(r, measurements=[m for m in r.measurements if not isinstance(m, RockObservations)])


def _config(model: str, **fixes) -> SmootherConfig:
    """No gate, no retraction: the test is about weighing fixes that all pass. The odometry's slip
    near the synthetic run's (5 % of the speed, changing every few seconds) and no slope term: with
    the yards' model (0.08 per sqrt(m), and 1.5 per rad of pitch on these hills, 10x the slip) the
    estimate leans on each fix alone and reads pessimistic whatever the fixes' model (final NEES
    1.2 for "bias"; 1.7 with this model, 2.4 with 0.02 / 0.01)."""
    f = FixConfig(gate_chi2=1e9, gate_distance_m=1e9, retract_chi2=1e9, retract_chi2_with_height=1e9,
                  correlation_model=model, correlation_length_m=L_M, bias_share=SHARE, **fixes)
    return SmootherConfig(fixes=f, odometry=OdometryNoiseConfig(sigma_forward_m_per_sqrtm=0.05, sigma_lateral_m_per_sqrtm=0.02,
                                                                sigma_forward_m_per_sqrtm_per_rad=0.0))


def _shared_error_fixes(run, rng, source: str = "rocks", rows=(1, 2, 3)) -> list[GlobalFix]:
    """A fix every 0.5 s whose error is a Gauss-Markov offset along the true path (correlation
    length L_M, SHARE of C_FIX) plus white noise, on time."""
    out, b, last = [], rng.multivariate_normal(np.zeros(3), SHARE * C_FIX), None
    for t in np.arange(EVERY_S, run.gt_t[-1] - 0.5, EVERY_S):
        T = run.gt_at(t)
        p = T[:3, 3]
        if last is not None:
            rho = np.exp(-np.linalg.norm(p[:2] - last[:2]) / L_M)
            b = rho * b + rng.multivariate_normal(np.zeros(3), (1 - rho**2) * SHARE * C_FIX)
        last = p
        e = b + rng.multivariate_normal(np.zeros(3), (1 - SHARE) * C_FIX)
        out.append(GlobalFix(t, t, p[0] + e[0], p[1] + e[1], yaw_of(T[:3, :3]) + e[2], C_FIX, source=source,
                             catalog_rows=rows))
    return out


def _final_nees(run, model: str, seed: int) -> float:
    rng = np.random.default_rng(seed)
    T0 = run.gt_T[0].copy()
    T0[:3, 3] += rng.multivariate_normal(np.zeros(3), START_COV[:3, :3])  # the start drawn from its prior
    sm = Isam2Smoother(PoseEstimate(run.gt_t[0], T0, START_COV), _config(model))
    out = drive(sm, run.measurements, _shared_error_fixes(run, rng))
    assert all(o.accepted for o in out.outcomes)
    est = sm.estimate()
    err = est.position_m[:2] - run.gt_at(est.t)[:2, 3]
    return float(err @ np.linalg.solve(est.cov[:2, :2], err))


@pytest.mark.slow
def test_the_shared_offset_as_variables_is_consistent_where_independent_fixes_are_not(run):
    n = 20
    bias = np.mean([_final_nees(run, "bias", s) for s in range(n)])
    independent = np.mean([_final_nees(run, "producer", s) for s in range(n)])
    # mean of 20 chi2(2) draws: 95 % inside [chi2.ppf(0.025, 40), chi2.ppf(0.975, 40)] / 20 = [1.22, 2.96]
    assert 1.22 <= bias <= 2.96, bias
    assert independent > 5.0, independent


def _offset_keys(sm: Isam2Smoother) -> list[int]:
    return sorted(k for k in sm.solver._alive if symbol_of(k) == OFFSET_SYMBOL)


def test_each_fix_of_a_source_gets_its_offset_reused_only_at_the_same_place_on_the_same_entries(run):
    rng = np.random.default_rng(0)
    fixes = _shared_error_fixes(run, rng)[:6]
    sm = Isam2Smoother(run.initial_pose, _config("bias"))
    drive(sm, run.measurements, fixes)
    assert len(_offset_keys(sm)) == 6  # the rover moves between fixes: a new offset each time
    # three fixes delivered together (the rover where it was), on the same entries: one offset
    sm2 = Isam2Smoother(run.initial_pose, _config("bias"))
    t0 = fixes[0].t_meas
    same = [dataclasses.replace(fixes[0]) for _ in range(3)]
    drive(sm2, [m for m in run.measurements if m.t <= t0 + 0.1], same)
    assert len(_offset_keys(sm2)) == 1
    # ... and on other entries: a fresh start (rho = 0), its own offset with its prior
    sm3 = Isam2Smoother(run.initial_pose, _config("bias"))
    other = [same[0], dataclasses.replace(same[1], catalog_rows=(7, 8, 9))]
    drive(sm3, [m for m in run.measurements if m.t <= t0 + 0.1], other)
    keys = _offset_keys(sm3)
    assert len(keys) == 2
    assert not any(sm3.solver.factors().at(i) is not None and set(sm3.solver.factors().at(i).keys()) == set(keys)
                   for i in range(sm3.solver.factors().size()))  # no Gauss-Markov step between them
    extra = sm3.stats().extra
    assert set(extra["fix_offset"]) == {"rocks"} and extra["n_offset_restarts"] == 0
    assert 0.0 < extra["fix_offset"]["rocks"]["sigma_x_m"] < 0.05


def test_a_source_without_an_offset_and_the_producer_model_add_no_variable(run):
    fixes = _shared_error_fixes(run, np.random.default_rng(1))[:4]
    for cfg, fx in [(_config("bias", bias_sources=("craters",)), fixes), (_config("producer"), fixes)]:
        sm = Isam2Smoother(run.initial_pose, cfg)
        out = drive(sm, run.measurements, fx)
        assert all(o.accepted for o in out.outcomes) and _offset_keys(sm) == []
    assert "fix_offset" not in sm.stats().extra
    # the height of an anchored fix, alone on the pose, is the terrain model's: no offset for it
    sm = Isam2Smoother(run.initial_pose, _config("bias"))
    t = fixes[1].t_meas
    z = float(run.gt_at(t)[2, 3])
    height = dataclasses.replace(fixes[1], height=FixHeight(z, 0.05**2, np.zeros(3))).height_only()
    out = drive(sm, [m for m in run.measurements if m.t <= t + 0.5], [fixes[0], height])
    assert all(o.accepted for o in out.outcomes) and len(_offset_keys(sm)) == 1


def test_in_the_fixed_lag_window_a_source_whose_offset_left_starts_afresh(run):
    rng = np.random.default_rng(2)
    fixes = _shared_error_fixes(run, rng)
    early, late = [f for f in fixes if f.t_meas < 5.0], [f for f in fixes if f.t_meas > 25.0][:3]
    sm = Isam2Smoother(run.initial_pose, dataclasses.replace(_config("bias"), fixed_lag_s=8.0, marginalize_every_s=0.0))
    out = drive(sm, run.measurements, early + late)
    assert all(o.accepted for o in out.outcomes)
    extra = sm.stats().extra
    assert extra["n_offset_restarts"] == 1  # 20 s without a fix: the early offsets left the window
    assert len(_offset_keys(sm)) == 3 and extra["fix_offset"]["rocks"]["sigma_x_m"] > 0


def test_a_wrong_fix_is_still_retracted_with_the_offset_model(run):
    cfg = SmootherConfig(fixes=FixConfig(gate_chi2=1e9, gate_distance_m=1e9, correlation_model="bias"))
    fixes = _shared_error_fixes(run, np.random.default_rng(4))[:20]
    wrong = dataclasses.replace(fixes[10], x_m=fixes[10].x_m + 6.0, y_m=fixes[10].y_m + 3.0, t_recv=fixes[10].t_recv + 0.01)
    sm = Isam2Smoother(run.initial_pose, cfg)
    out = drive(sm, run.measurements, fixes[:11] + [wrong] + fixes[11:])
    by_fix = {id(o.fix): o for o in out.outcomes}
    assert by_fix[id(wrong)].reason.startswith("retracted")
    assert sum(o.accepted for o in out.outcomes) == 20
    err = sm.estimate().position_m[:2] - run.gt_at(sm.estimate().t)[:2, 3]
    assert np.hypot(*err) < 0.2


def _numerical_jacobians(factor, values: gtsam.Values, eps: float = 1e-6) -> list[np.ndarray]:
    out = []
    for key in factor.keys():  # noqa: SIM118 (a gtsam factor is not iterable)
        base = factor.unwhitenedError(values)
        is_pose = symbol_of(key) == "x"
        J = np.zeros((len(base), 6 if is_pose else 3))
        for j in range(J.shape[1]):
            v = gtsam.Values(values)
            d = np.zeros(J.shape[1])
            d[j] = eps
            if is_pose:
                v.update(key, values.atPose3(key).retract(d))
            else:
                v.update(key, values.atVector(key) + d)
            J[:, j] = (factor.unwhitenedError(v) - base) / eps
        out.append(J)
    return out


def test_the_fix_factor_with_an_offset_and_the_gauss_markov_step_match_numerical_derivatives():
    rng = np.random.default_rng(5)
    X0, O0, O1 = gtsam.Symbol("x", 0).key(), gtsam.Symbol("o", 0).key(), gtsam.Symbol("o", 1).key()
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.05, -0.03, 0.7), np.array([1.0, 2.0, 0.3]))
    T_rel = gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([0.4, 0.05, 0.0])).matrix()
    g = np.array([0.2, -0.1, 0.0])
    G = np.vstack([np.eye(3), g])
    target = np.array([1.5, 2.3, 0.75, 0.4])
    values = gtsam.Values()
    values.insert(X0, T)
    values.insert(O0, rng.normal(0, 0.1, 3))
    values.insert(O1, rng.normal(0, 0.1, 3))
    cov_fix, cov_gm = np.diag([0.01, 0.01, 0.001, 0.02]), np.diag([0.01, 0.02, 0.001])
    # a kernel scale far beyond the residual: the linearization is the Gaussian one
    fix = make_fix_factor(X0, T_rel, target, cov_fix, 1e9, O0, G)
    gm = make_gauss_markov_factor(O0, O1, 0.7, cov_gm)
    for factor, cov in ((fix, cov_fix), (gm, cov_gm)):
        A, _ = factor.linearize(values).jacobian()  # whitened, the factor's keys in order
        num = gtsam.noiseModel.Gaussian.Covariance(cov).Whiten(np.hstack(_numerical_jacobians(factor, values)))
        assert np.allclose(A, num, atol=1e-4 * np.abs(num).max()), (A, num)
    r = fix.unwhitenedError(values)
    assert np.isclose(r[3], values.atPose3(X0).compose(gtsam.Pose3(T_rel)).translation()[2] - target[3]
                      + g @ values.atVector(O0))  # the height row moves with the offset along the gradient
    with pytest.raises(ValueError, match="offset_rows"):
        make_fix_factor(X0, T_rel, target, np.eye(4), 2.0, O0, np.eye(3))


def test_unshared_takes_the_share_out_of_the_match_and_carries_the_height():
    C = np.diag([0.04, 0.09, 0.001])
    rel = np.diag([0.01, 0.01])
    g = np.array([0.3, -0.2, 0.0])
    fix = GlobalFix(1.0, 2.0, 0.0, 0.0, 0.0, 2.0 * C + np.pad(rel, (0, 1)), correlation_scale=2.0, cov_relative_xy=rel,
                    height=FixHeight(1.0, 0.01 + g @ (2.0 * C + np.pad(rel, (0, 1))) @ g, (2.0 * C + np.pad(rel, (0, 1))) @ g))
    w = fix.unshared(0.9)
    white = 0.1 * C + np.pad(rel, (0, 1))
    assert np.allclose(w.cov_xyyaw, white) and w.correlation_scale == 1.0
    assert np.allclose(w.height.cov_xyyaw, white @ g) and np.isclose(w.height.var_m2, 0.01 + g @ white @ g)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(MeasurementError, match="share"):
            fix.unshared(bad)


@pytest.mark.parametrize("symbol", ["g", "b", "o"])
def test_a_kind_cannot_take_a_symbol_of_the_smoothers_own_variables(symbol):
    with pytest.raises(KindLayerError, match="symbol"):
        LandmarkKind("pebbles", RockObservations, rank=9, symbol=symbol)

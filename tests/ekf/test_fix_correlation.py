"""Correlated fixes: fixes whose errors share a Gauss-Markov offset along the path, fused by the
filter with the offset as a state (``fix_gate.correlation_model`` "bias") are consistent; taken
as independent they make it overconfident. Odometry only (no rocks), so the fixes' errors are
what the position error is made of."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.geometry import yaw_of
from reloc.measurements import GlobalFix

L_M, SHARE = 1.0, 0.9  # correlation length of the shared error (m of path), its share of the fix's variance
C_FIX = np.diag([0.05**2, 0.05**2, 0.01**2])
START_COV = np.diag([0.3**2, 0.3**2, 0.01**2, 1e-4, 1e-4, 0.05**2])
EVERY = 15  # a fix every 0.5 s (0.125 m of path)


@pytest.fixture(scope="module")
def run():
    return simulate(5, duration_s=20.0, n_rocks=1)


def _trial(run, cfg: EkfConfig, seed: int) -> np.ndarray:
    """Final planar position error whitened by the filter's covariance, for one draw of the start
    and the fixes' errors (shared offset first-order Gauss-Markov along the true path)."""
    rng = np.random.default_rng(seed)
    T0 = np.eye(4)
    T0[:3, 3] = rng.multivariate_normal(np.zeros(3), START_COV[:3, :3])  # the start drawn from its prior
    ekf = EkfSlam(PoseEstimate(0.0, T0, START_COV), cfg)
    b = rng.multivariate_normal(np.zeros(3), SHARE * C_FIX)
    last = None
    for k, step in enumerate(run.steps, start=1):
        ekf.predict(step)
        if k % EVERY:
            continue
        p = run.truth_p[k]
        if last is not None:  # the offset decorrelates with the path driven since the last fix
            rho = np.exp(-np.linalg.norm(p[:2] - last[:2]) / L_M)
            b = rho * b + rng.multivariate_normal(np.zeros(3), (1 - rho**2) * SHARE * C_FIX)
        last = p
        e = b + rng.multivariate_normal(np.zeros(3), (1 - SHARE) * C_FIX)
        fix = GlobalFix(run.t[k], run.t[k], p[0] + e[0], p[1] + e[1], yaw_of(run.truth_R[k]) + e[2], C_FIX,
                        source="rocks")
        assert ekf.apply_fix(fix).accepted
    est = ekf.estimate()
    err = est.position_m[:2] - run.truth_p[-1, :2]
    return float(err @ np.linalg.solve(est.cov[:2, :2], err))


def _gate(**kw) -> EkfConfig:
    """No gate, no consensus; the fixes as they came (``producer``) unless ``kw`` says otherwise."""
    kw.setdefault("correlation_model", "producer")
    return EkfConfig(yaw_rate_bias_sigma_radps=0.0,
                     fix_gate=dataclasses.replace(EkfConfig().fix_gate, chi2=1e9, consensus_n=0, **kw))


def test_the_shared_offset_as_a_state_is_consistent_where_independent_fixes_are_not(run):
    n = 30
    bias = np.mean([_trial(run, _gate(correlation_model="bias", correlation_length_m=L_M, bias_share=SHARE), s)
                    for s in range(n)])
    independent = np.mean([_trial(run, _gate(), s) for s in range(n)])
    # mean of n chi2(2) draws: 95 % inside [chi2.ppf(0.025, 2n), chi2.ppf(0.975, 2n)] / n
    assert 1.4 <= bias <= 2.75, bias
    assert independent > 5.0, independent


def test_a_fix_from_a_source_without_an_offset_state_is_taken_as_it_came(run):
    cfg = _gate(correlation_model="bias", bias_sources=("craters",))
    a, b = EkfSlam(PoseEstimate(0.0, np.eye(4), START_COV), cfg), EkfSlam(PoseEstimate(0.0, np.eye(4), START_COV), _gate())
    assert a.full_covariance().shape[0] == b.full_covariance().shape[0] + 3  # the craters' offset
    for ekf in (a, b):
        for k, step in enumerate(run.steps[:60], start=1):
            ekf.predict(step)
        p = run.truth_p[60]
        assert ekf.apply_fix(GlobalFix(run.t[60], run.t[60], p[0], p[1], yaw_of(run.truth_R[60]), C_FIX,
                                       source="rocks")).accepted
    assert np.allclose(a.estimate().cov, b.estimate().cov) and np.allclose(a.estimate().T_world_base,
                                                                           b.estimate().T_world_base)


def test_fixes_on_other_catalog_entries_share_no_offset(run):
    """Two fixes at one place: on the same catalog entries the second adds little (the offset is
    the same), on entries the first did not use it is a new draw of the offset (a turn in place
    brings other rocks into view)."""
    cfg = _gate(correlation_model="bias", correlation_length_m=L_M, bias_share=SHARE)
    p, yaw = run.truth_p[60], yaw_of(run.truth_R[60])
    var = {}
    for name, rows in [("once", None), ("same", (1, 2, 3)), ("other", (4, 5, 6))]:
        ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), START_COV), cfg)
        for step in run.steps[:60]:
            ekf.predict(step)
        ekf.apply_fix(GlobalFix(run.t[60], run.t[60], p[0], p[1], yaw, C_FIX, source="rocks", catalog_rows=(1, 2, 3)))
        if rows is not None:
            ekf.apply_fix(GlobalFix(run.t[60], run.t[60], p[0], p[1], yaw, C_FIX, source="rocks", catalog_rows=rows))
        var[name] = ekf.estimate().cov[:2, :2].trace()
    assert var["same"] == pytest.approx(var["once"], rel=0.1)
    assert var["other"] < 0.6 * var["once"]


def test_the_height_of_an_anchored_fix_leaves_its_sources_offset_alone(run):
    """An anchored fix puts its entries on the landmarks and its height, alone, on the pose
    (``GlobalFix.height_only``: planar sigmas of a kilometre). That height is the terrain model's,
    not the catalog's: it must not take the catalog's shared offset, whose covariance it would
    have opened by (1 - rho^2) x 0.9 x a kilometre squared."""
    from reloc.measurements import FixHeight

    cfg = _gate(correlation_model="bias", correlation_length_m=L_M, bias_share=SHARE)
    ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), START_COV), cfg)
    for step in run.steps[:60]:
        ekf.predict(step)
    p, yaw = run.truth_p[60], yaw_of(run.truth_R[60])
    ekf.apply_fix(GlobalFix(run.t[60], run.t[60], p[0], p[1], yaw, C_FIX, source="rocks", catalog_rows=(1, 2, 3)))
    before = ekf.stats().extra["fix_offset"]["rocks"]
    for step in run.steps[60:90]:  # the rover moves on: the offset would decorrelate
        ekf.predict(step)
    p = run.truth_p[90]
    with_height = GlobalFix(run.t[90], run.t[90], p[0], p[1], yaw_of(run.truth_R[90]), C_FIX, source="rocks",
                            catalog_rows=(1, 2, 3), height=FixHeight(float(p[2]), 0.05**2, np.zeros(3)))
    assert ekf.apply_fix(with_height.height_only()).accepted
    assert ekf.stats().extra["fix_offset"]["rocks"] == before


def _consensus_cfg(opens: str) -> EkfConfig:
    return EkfConfig(yaw_rate_bias_sigma_radps=0.0,
                     fix_gate=dataclasses.replace(EkfConfig().fix_gate, correlation_model="bias", consensus_opens=opens))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_consensus_on_a_shared_offset_opens_the_offset_as_well_as_the_pose(seed):
    """Fixes on the same catalog entries all 0.09 rad off in yaw (4.5 sigma of their own 0.02 rad:
    a match whose covariance is short, as on my2021 at 116-142 s) and a filter that is right: the
    gate rejects the first, the third completes a consensus. Opening only the pose turns the
    heading to the fixes and leaves it there, far outside its own sigma; opening the source's
    offset as well (the default) keeps the heading within 3 sigma of the truth and well away
    from the fixes."""
    run = simulate(seed, duration_s=20.0, n_rocks=1)
    start = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))
    cov = np.diag([0.1**2, 0.1**2, 0.02**2])
    off = 0.09
    ends = {}
    for opens in ("pose", "pose_and_offset"):
        ekf = EkfSlam(start, _consensus_cfg(opens))
        outcomes = []
        for k, step in enumerate(run.steps, start=1):
            ekf.predict(step)
            if k % 30:
                continue
            p = run.truth_p[k]
            outcomes.append(ekf.apply_fix(GlobalFix(run.t[k], run.t[k], p[0], p[1], yaw_of(run.truth_R[k]) + off, cov,
                                                    source="rocks", catalog_rows=(1, 2, 3))))
        assert [o.accepted for o in outcomes[:3]] == [False, False, True]
        assert all(o.accepted for o in outcomes[3:])
        assert ekf.stats().extra["n_consensus_resets"] == 1
        est = ekf.estimate()
        ends[opens] = (float(yaw_of(est.T_world_base) - yaw_of(run.truth_R[-1])), float(np.sqrt(est.cov[5, 5])))
        offsets = ekf.stats().extra["fix_offset"]
        assert set(offsets) == {"rocks"}  # the craters sent no fix
        # the fixes agree with pose + offset: what the pose did not take, the offset did
        assert np.radians(offsets["rocks"]["yaw_deg"]) == pytest.approx(off - ends[opens][0], abs=0.01)
    e_pose, s_pose = ends["pose"]
    assert abs(e_pose) > 0.4 * off and abs(e_pose) > 3.0 * s_pose  # the pose took the offset, and is sure of it
    e_both, s_both = ends["pose_and_offset"]
    assert abs(e_both) <= 3.0 * s_both and abs(e_both) < 0.25 * off


def test_a_replayed_consensus_opens_the_same_covariance_again():
    """A late fix that carries no information, measured before a consensus fix, rolls the filter
    back past it: the replay applies the consensus fix with the same inflation of the pose and the
    offset, so the state ends where it was."""
    run = simulate(1, duration_s=20.0, n_rocks=1)
    start = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))
    ekf = EkfSlam(start, _consensus_cfg("pose_and_offset"))
    cov = np.diag([0.1**2, 0.1**2, 0.02**2])
    for k, step in enumerate(run.steps, start=1):
        ekf.predict(step)
        if k % 30 == 0 and k <= 150:
            p = run.truth_p[k]
            ekf.apply_fix(GlobalFix(run.t[k], run.t[k], p[0], p[1], yaw_of(run.truth_R[k]) + 0.09, cov,
                                    source="rocks", catalog_rows=(1, 2, 3)))
    assert ekf.stats().extra["n_consensus_resets"] == 1  # at step 90
    before_P, before_T = ekf.full_covariance().copy(), ekf.estimate().T_world_base.copy()
    p = run.truth_p[75]
    late = GlobalFix(run.t[75], run.t[-1], p[0], p[1], yaw_of(run.truth_R[75]), np.diag([1e8, 1e8, 1e4]), source="orbit")
    assert ekf.apply_fix(late).accepted
    assert np.allclose(ekf.estimate().T_world_base, before_T, atol=1e-6)
    assert np.allclose(ekf.full_covariance(), before_P, rtol=1e-4, atol=1e-9)

"""Bad inputs get a clear EkfInputError and leave the state untouched; wrong fixes are gated."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig, FixGateConfig
from ekf.errors import EkfInputError
from ekf.slam import EkfSlam
from reloc.backend import Backend, PoseEstimate
from reloc.errors import MeasurementError
from reloc.geometry import yaw_of
from reloc.measurements import GlobalFix, RockObservations

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))


@pytest.fixture(scope="module")
def run():
    return simulate(11, duration_s=8.0, n_rocks=80)


def fed(run, upto=None, config=None):
    ekf = EkfSlam(START, config)
    for k, step in enumerate(run.steps[:upto]):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
    return ekf


def snapshot(ekf):
    e = ekf.estimate()
    return e.t, e.T_world_base.copy(), ekf.full_covariance(), len(ekf.trajectory()), ekf.stats().n_predict


def assert_untouched(ekf, snap):
    now = snapshot(ekf)
    assert now[0] == snap[0] and now[3] == snap[3] and now[4] == snap[4]
    assert np.array_equal(now[1], snap[1]) and np.array_equal(now[2], snap[2])


def test_is_a_backend(run):
    ekf = fed(run, 30)
    assert isinstance(ekf, Backend) and ekf.name == "ekf"
    P = ekf.full_covariance()
    assert np.array_equal(P, P.T) and np.linalg.eigvalsh(P)[0] > 0


def test_nan_step_rejected_state_untouched(run):
    ekf = fed(run, 100)
    snap = snapshot(ekf)
    good = run.steps[100]
    bad = dataclasses.replace(good, v_mps=float("nan"))
    with pytest.raises(EkfInputError, match="NaN"):
        ekf.predict(bad)
    R_bad = good.R_ref_base1.copy()
    R_bad[0, 0] = np.nan
    with pytest.raises(EkfInputError, match="NaN"):
        ekf.predict(dataclasses.replace(good, R_ref_base1=R_bad))
    with pytest.raises(EkfInputError, match="not a rotation"):
        ekf.predict(dataclasses.replace(good, R_ref_base1=2.0 * good.R_ref_base1))
    assert_untouched(ekf, snap)
    ekf.predict(good)  # still usable
    assert isinstance(EkfInputError("x"), MeasurementError)


def test_out_of_order_inputs_rejected_state_untouched(run):
    ekf = fed(run, 120)
    snap = snapshot(ekf)
    with pytest.raises(EkfInputError, match="out of order"):
        ekf.predict(run.steps[50])
    frame_k = max(k for k in run.frames if k < 100)
    with pytest.raises(EkfInputError, match="out of order"):
        ekf.observe(run.frames[frame_k])
    assert_untouched(ekf, snap)


def test_nan_observation_rejected(run):
    ekf = fed(run, 120)
    snap = snapshot(ekf)
    good = run.frames[max(k for k in run.frames if k >= 120)]
    bad = object.__new__(RockObservations)  # bypasses the constructor's own validation
    for name in ("xyz_base_m", "cov_base_m2", "size_m", "score"):
        object.__setattr__(bad, name, getattr(good, name).copy())
    object.__setattr__(bad, "t", good.t)
    bad.xyz_base_m[0, 1] = np.nan
    with pytest.raises(EkfInputError, match="NaN"):
        ekf.observe(bad)
    assert_untouched(ekf, snap)


def fix_at(run, k, dx=0.0, dyaw=0.0, sigma=0.1):
    return GlobalFix(run.t[k], run.t[k], run.truth_p[k, 0] + dx, run.truth_p[k, 1], yaw_of(run.truth_R[k]) + dyaw,
                     np.diag([sigma**2, sigma**2, 0.02**2]))


def test_wrong_fix_10m_rejected_by_distance_gate(run):
    ekf = fed(run, 200)
    snap = snapshot(ekf)
    out = ekf.apply_fix(fix_at(run, 200, dx=10.0))
    assert not out.accepted and out.reason.startswith("distance gate")
    assert_untouched(ekf, snap)
    assert ekf.stats().n_fixes_rejected == 1 and ekf.stats().extra["fix_reject_reasons"] == {"distance": 1}


@pytest.mark.parametrize("sigmas, accepted", [(4.0, True), (0.0, False)])
def test_the_distance_gate_opens_with_the_filters_own_spread(sigmas, accepted):
    """A filter that has drifted and knows it (5 m sigma) takes a right fix 6 m away: the gate is
    max(distance_m, distance_sigmas x the innovation's largest sigma), 20 m here; with the
    sigmas off, the 3 m of the reference design refuse it. A confident filter (0.5 m) still
    refuses a fix 4 m away at the metres: 4 sigma of it is 2 m."""
    cfg = EkfConfig(fix_gate=FixGateConfig(distance_sigmas=sigmas))
    lost = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([25.0, 25.0, 0.01, 1e-4, 1e-4, 1e-4])), cfg)
    out = lost.apply_fix(GlobalFix(0.0, 0.0, 6.0, 0.5, 0.0, np.diag([0.01, 0.01, 1e-4])))
    assert out.accepted is accepted
    if accepted:  # the estimate goes (almost) where the fix is: 25 m^2 against 0.01 m^2
        np.testing.assert_allclose(lost.estimate().position_m[:2], [6.0, 0.5], atol=0.01)
        assert out.mahalanobis_d2 < 16.27
    else:
        assert out.reason == "distance gate 6.02 m > 3.00 m"
    sure = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([0.25, 0.25, 0.01, 1e-4, 1e-4, 1e-4])), cfg)
    out = sure.apply_fix(GlobalFix(0.0, 0.0, 4.0, 0.0, 0.0, np.diag([0.01, 0.01, 1e-4])))
    assert not out.accepted and out.reason == "distance gate 4.00 m > 3.00 m"


def test_yaw_and_mahalanobis_gates(run):
    ekf = fed(run, 200, EkfConfig(fix_gate=FixGateConfig(distance_m=100.0)))
    out = ekf.apply_fix(fix_at(run, 200, dyaw=np.radians(30)))
    assert not out.accepted and out.reason.startswith("yaw gate")
    # inside the 100 m distance gate but 10 m away from a filter that is sure within centimetres
    out = ekf.apply_fix(fix_at(run, 200, dx=10.0))
    assert not out.accepted and out.reason.startswith("Mahalanobis") and out.mahalanobis_d2 > 100
    good = ekf.apply_fix(fix_at(run, 200, dx=0.02))
    assert good.accepted and good.mahalanobis_d2 < 16.27
    st = ekf.stats()
    assert (st.n_fixes_accepted, st.n_fixes_rejected) == (1, 2)


def test_fix_pulls_estimate_and_shrinks_covariance(run):
    ekf = fed(run, 200)
    before = ekf.estimate()
    # a perfect fix 0.5 m from a confident estimate is gated out, so loosen the filter first
    ekf2 = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([1.0, 1.0, 0.01, 1e-4, 1e-4, 0.01])))
    out = ekf2.apply_fix(GlobalFix(0.0, 0.0, 0.5, -0.3, 0.1, np.diag([0.01, 0.01, 0.001])))
    assert out.accepted
    e = ekf2.estimate()
    # the scalar Kalman answers: prior var 1 / 0.01, measurement var 0.01 / 0.001
    assert np.allclose(e.position_m[:2], np.array([0.5, -0.3]) / 1.01, atol=1e-9)
    assert e.yaw_rad == pytest.approx(0.1 * 0.01 / 0.011, abs=1e-9)
    assert e.cov[0, 0] == pytest.approx(0.01 / 1.01) and e.cov[5, 5] == pytest.approx(1e-5 / 0.011)
    assert before.t == ekf.estimate().t


def test_fix_ahead_of_filter_rejected(run):
    ekf = fed(run, 100)
    out = ekf.apply_fix(fix_at(run, 200))
    assert not out.accepted and out.reason.startswith("ahead")


def test_map_hygiene_and_bound(run):
    cfg = EkfConfig(max_landmarks=10)
    ekf = fed(run, None, cfg)
    st = ekf.stats()
    assert ekf.state_vector_size <= 6 + 2 + 2 * 3 + 3 * 10  # pose, yaw-rate bias, slip, 2 fix offsets, <= 10 landmarks
    assert st.extra["n_evicted"] > 0
    m = ekf.landmark_map("rocks")
    assert len(m) <= 10 and np.all(m.n_obs >= cfg.book.confirm_n_obs)
    assert np.all(np.linalg.eigvalsh(m.cov_world_m2) > 0)
    # every confirmed landmark sits near a true rock
    d = np.linalg.norm(m.xyz_world_m[:, None, :] - run.rocks[None, :, :], axis=2).min(axis=1)
    assert np.all(d < 0.5)


def test_fixes_close_in_time_are_not_counted_as_independent():
    cfg = EkfConfig(fix_gate=FixGateConfig(correlation_s=30.0))
    ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([1.0, 1.0, 0.01, 1e-4, 1e-4, 0.01])), cfg)
    fix = GlobalFix(0.0, 0.0, 0.0, 0.0, 0.0, np.diag([0.01, 0.01, 0.001]))
    assert ekf.apply_fix(fix).accepted
    v1 = 0.01 / 1.01
    assert ekf.estimate().cov[0, 0] == pytest.approx(v1)
    assert ekf.apply_fix(fix).accepted  # the second one counts with twice its covariance
    assert ekf.estimate().cov[0, 0] == pytest.approx(v1 * 0.02 / (v1 + 0.02))
    plain = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([1.0, 1.0, 0.01, 1e-4, 1e-4, 0.01])),
                    EkfConfig(fix_gate=FixGateConfig(correlation_s=0.0)))
    plain.apply_fix(fix)
    plain.apply_fix(fix)
    assert plain.estimate().cov[0, 0] == pytest.approx(v1 * 0.01 / (v1 + 0.01))


def test_bad_config_is_named():
    from reloc.config import config_from_dict
    from reloc.errors import ConfigError

    with pytest.raises(ConfigError, match="max_landmarks"):
        EkfConfig(max_landmarks=0)
    with pytest.raises(ConfigError, match="unknown key"):
        config_from_dict(EkfConfig, {"motion": {"fwd_sigma": 1.0}})
    cfg = config_from_dict(EkfConfig, {"max_landmarks": 50, "fix_gate": {"distance_m": 5}})
    assert cfg.max_landmarks == 50 and cfg.fix_gate.distance_m == 5.0

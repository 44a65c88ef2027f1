"""The wheel-slip monitor: visual translation between two landmark frames, slip detected and
corrected only when the landmarks contradict the wheels, the correction's uncertainty carried
into both back-ends' process noise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reloc.errors import ConfigError
from reloc.geometry import exp_so3
from reloc.odometry import OdometryStep
from reloc.slip import SlipConfig, SlipMonitor, visual_translation

SIGMA = 0.02  # m, per point and axis


@dataclasses.dataclass
class Frame:
    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz_base_m)


def _rocks(rng, n=25):
    return np.column_stack([rng.uniform(1.0, 7.0, n), rng.uniform(-3.0, 3.0, n), rng.uniform(-0.3, 0.1, n)])


def _see(rng, rocks_world, R_wb, p_wb, t, n_clutter=3, drop=0.2):
    """Noisy detections of the rocks in base_link (some missed) plus clutter."""
    z = (rocks_world - p_wb) @ R_wb
    keep = rng.random(len(z)) > drop
    z = z[keep] + rng.normal(0.0, SIGMA, (int(keep.sum()), 3))
    clutter = np.column_stack([rng.uniform(1, 7, n_clutter), rng.uniform(-3, 3, n_clutter), np.zeros(n_clutter)])
    z = np.vstack([z, clutter])
    return Frame(t, z, np.tile(np.eye(3) * SIGMA**2, (len(z), 1, 1)))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), dx=st.floats(0.0, 0.4), dy=st.floats(-0.05, 0.05),
       yaw=st.floats(-0.1, 0.1), slip=st.floats(0.0, 1.0))
def test_visual_translation_recovers_the_motion_within_its_covariance(seed, dx, dy, yaw, slip):
    rng = np.random.default_rng(seed)
    rocks = _rocks(rng)
    d_true = np.array([dx, dy, 0.0])
    R = exp_so3(np.array([0.0, 0.0, yaw]))
    a = _see(rng, rocks, np.eye(3), np.zeros(3), 0.0)
    b = _see(rng, rocks, R, d_true, 1.0)
    d_wheel = d_true / max(1.0 - slip, 0.2) if dx > 0 else np.array([0.3, 0.0, 0.0])
    vt = visual_translation(a.xyz_base_m, a.cov_base_m2, b.xyz_base_m, b.cov_base_m2, R, d_wheel, SlipConfig())
    assert vt is not None
    e = vt.d_m - d_true
    assert e @ np.linalg.solve(vt.cov_m2, e) < 25.0  # chi2(3) far tail: 5 sigma
    assert vt.n_inliers >= 6  # of ~16 rocks in both frames


def test_visual_translation_declines_without_enough_common_landmarks():
    rng = np.random.default_rng(0)
    a = _see(rng, _rocks(rng, 3), np.eye(3), np.zeros(3), 0.0, n_clutter=0, drop=0.0)
    assert visual_translation(a.xyz_base_m, a.cov_base_m2, a.xyz_base_m, a.cov_base_m2, np.eye(3),
                              np.array([0.2, 0, 0]), SlipConfig()) is None
    # two unrelated clouds: no translation that many pairs agree on
    b = _see(rng, _rocks(rng, 25), np.eye(3), np.zeros(3), 1.0, n_clutter=0, drop=0.0)
    c = _see(rng, _rocks(rng, 25), np.eye(3), np.zeros(3), 2.0, n_clutter=0, drop=0.0)
    assert visual_translation(b.xyz_base_m, b.cov_base_m2, c.xyz_base_m, c.cov_base_m2, np.eye(3),
                              np.array([0.2, 0, 0]), SlipConfig()) is None


def test_a_periodic_field_is_ambiguous():
    """Rocks on a 0.3 m grid along the motion: shifts of one period explain the frame as well."""
    g = np.array([[1.0 + 0.3 * i, 0.5 * j, 0.0] for i in range(12) for j in range(-3, 4)])
    cov = np.tile(np.eye(3) * 1e-4, (len(g), 1, 1))
    shifted = g - np.array([0.1, 0.0, 0.0])
    assert visual_translation(g, cov, shifted, cov, np.eye(3), np.array([0.6, 0, 0]), SlipConfig()) is None


def _steps(t0, t1, v, dt=0.02):
    R = np.eye(3)
    return [OdometryStep(t, t + dt, v, 0.0, R, R, np.zeros(3)) for t in np.arange(t0, t1 - 1e-9, dt)]


def _drive(cfg, stuck=(10.0, 30.0), blind=None, v=0.1, t_end=45.0, seed=1):
    """Rover commanded at v along x; truly stuck in ``stuck``; frames at 1 Hz (none in ``blind``).
    Returns (monitor, corrected distance, true distance, steps)."""
    rng = np.random.default_rng(seed)
    rocks = np.column_stack([rng.uniform(-2, 12, 200), rng.uniform(-3, 3, 200), np.zeros(200)])
    mon = SlipMonitor(cfg)
    x_true = x_est = 0.0
    out = []
    for step in _steps(0.0, t_end, v):
        moving = not (stuck[0] <= step.t0 < stuck[1])
        x_true += v * step.dt if moving else 0.0
        c = mon.correct(step)
        out.append(c)
        x_est += c.v_mps * c.dt
        k = round(step.t1 / 0.02)
        if k % 50 == 0 and not (blind and blind[0] <= step.t1 < blind[1]):
            f = _see(rng, rocks, np.eye(3), np.array([x_true, 0.0, 0.0]), step.t1)
            near = (f.xyz_base_m[:, 0] > 0.5) & (f.xyz_base_m[:, 0] < 8)
            mon.observe("rocks", Frame(f.t, f.xyz_base_m[near], f.cov_base_m2[near]))
    return mon, x_est, x_true, out


def test_a_stuck_rover_is_detected_and_its_odometry_corrected_then_released():
    mon, x_est, x_true, steps = _drive(SlipConfig())
    assert x_true == pytest.approx(0.1 * 25.0, abs=1e-6)
    # uncorrected the wheels would say 4.5 m; the correction leaves what a check or two lags
    assert abs(x_est - x_true) < 0.35
    st_ = mon.stats()
    assert st_["n_detections"] >= 1 and st_["max_slip"] > 0.8
    assert 17.0 <= st_["corrected_s"] <= 25.0
    slipping = [c for c in mon.checks if c.slipping]
    assert all(9.0 <= c.t <= 32.0 for c in slipping)  # never outside the stuck spell (+ one check)
    assert not mon.active  # released once the wheels and the landmarks agree again
    corrected = [s for s in steps if s.extra_forward_var_m2 > 0]
    assert corrected and all(s.v_mps < 0.05 for s in corrected if 13.0 <= s.t0 < 29.0)


def test_a_free_rover_is_never_corrected():
    mon, x_est, x_true, steps = _drive(SlipConfig(), stuck=(1e9, 1e9))
    assert mon.stats()["n_slipping_checks"] == 0 and len(mon.checks) >= 20
    assert x_est == pytest.approx(x_true)
    assert all(s.extra_forward_var_m2 == 0.0 for s in steps)


def test_a_blind_camera_releases_the_correction_after_hold_s():
    *_, steps = _drive(SlipConfig(hold_s=3.0), stuck=(10.0, 40.0), blind=(20.0, 40.0))
    corrected_t = [s.t0 for s in steps if s.extra_forward_var_m2 > 0]
    assert corrected_t and max(corrected_t) < 20.0 + 3.0 + 0.05


def test_disabled_monitor_changes_nothing():
    mon, x_est, _, _ = _drive(SlipConfig(enabled=False))
    assert x_est == pytest.approx(0.1 * 45.0) and mon.stats()["n_checks"] == 0


def test_config_is_range_checked_by_key():
    from reloc.config import config_from_dict

    with pytest.raises(ConfigError, match="min_slip"):
        config_from_dict(SlipConfig, {"min_slip": 1.5})
    with pytest.raises(ConfigError, match="hold_s"):
        SlipConfig(hold_s=0.0)


def test_extra_forward_variance_reaches_both_back_ends_and_splits_in_time():
    from ekf.config import MotionNoiseConfig
    from ekf.motion import process_noise_body, split_step
    from fgslam.smoother.config import OdometryNoiseConfig
    from fgslam.smoother.odometry_factors import step_motion

    R = np.eye(3)
    plain = OdometryStep(0.0, 0.1, 0.0, 0.0, R, R, np.zeros(3))
    wide = dataclasses.replace(plain, extra_forward_var_m2=4e-4)
    assert process_noise_body(wide, MotionNoiseConfig())[0][0] == pytest.approx(
        process_noise_body(plain, MotionNoiseConfig())[0][0] + 4e-4)
    assert step_motion(wide, OdometryNoiseConfig())[1][3, 3] == pytest.approx(
        step_motion(plain, OdometryNoiseConfig())[1][3, 3] + 4e-4)
    a, b = split_step(wide, 0.025)
    assert a.extra_forward_var_m2 + b.extra_forward_var_m2 == pytest.approx(4e-4)
    assert a.extra_forward_var_m2 == pytest.approx(1e-4)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.05, 3.0))
def test_the_region_search_finds_exactly_the_pairs_of_the_whole_array(seed, radius):
    """The k-d tree's proposals are those of all N x M differences inside the region, in the same
    (i, j) order (points on a grid, so that pairs fall near the radius), and a pair exactly at
    the radius is kept, as the whole array's test keeps it."""
    from reloc.slip import _pairs_in_region

    _, ii, jj = _pairs_in_region(np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), np.zeros((1, 3)), np.zeros(3), 1.0)
    assert ii.tolist() == [0] and jj.tolist() == [0]

    rng = np.random.default_rng(seed)
    p_ref = np.round(rng.uniform(-6.0, 6.0, (int(rng.integers(1, 60)), 3)), 1)  # grid: ties at the radius
    q = np.round(rng.uniform(-6.0, 6.0, (int(rng.integers(1, 60)), 3)), 1)
    centre = np.round(rng.uniform(-1.0, 1.0, 3), 1)
    radius = round(radius, 1)
    D_all = (p_ref[:, None, :] - q[None, :, :]).reshape(-1, 3)
    ii_all, jj_all = np.divmod(np.arange(D_all.shape[0]), len(q))
    keep = np.linalg.norm(D_all - centre, axis=1) <= radius
    D, ii, jj = _pairs_in_region(p_ref, q, centre, radius)
    np.testing.assert_array_equal(ii, ii_all[keep])
    np.testing.assert_array_equal(jj, jj_all[keep])
    np.testing.assert_array_equal(D, D_all[keep])

"""Systematic stereo errors: per-rock centre error, camera mounting and depth scale."""

from __future__ import annotations

import numpy as np

from sim.config import StereoConfig
from sim.sensors.stereo import StereoBias, biased_points


def _no_calibration_error(frac: np.ndarray) -> StereoBias:
    return StereoBias(frac, np.eye(3), 1.0)


def test_centre_error_moves_the_point_along_the_line_of_sight_by_the_rock_fraction():
    pc = np.array([[0.0, 0.0, 5.0], [3.0, 1.0, 4.0], [-1.0, 0.5, 3.0]])
    radius = np.array([0.2, 0.4, 0.3])
    frac = np.array([0.5, 1.0, -0.4])  # negative: behind the centre
    out = biased_points(pc, radius, frac, _no_calibration_error(frac))
    shift = np.linalg.norm(pc, axis=1) - np.linalg.norm(out, axis=1)
    np.testing.assert_allclose(shift, frac * radius, atol=1e-12)
    # along the line of sight only: the direction from the camera is unchanged
    np.testing.assert_allclose(out / np.linalg.norm(out, axis=1, keepdims=True),
                               pc / np.linalg.norm(pc, axis=1, keepdims=True), atol=1e-12)


def test_mounting_error_rotates_and_depth_scale_stretches_every_point_alike():
    rng = np.random.default_rng(3)
    cfg = StereoConfig(centre_error_frac=0.0, extrinsic_sigma_deg=0.5, depth_scale_sigma=0.01)
    bias = StereoBias.draw(4, cfg, rng)
    np.testing.assert_allclose(bias.R_cam_err @ bias.R_cam_err.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(bias.R_cam_err) > 0
    angle = np.degrees(np.arccos(np.clip((np.trace(bias.R_cam_err) - 1) / 2, -1, 1)))
    assert 0.0 < angle < 5 * 0.5 * np.sqrt(3)
    pc = rng.normal(size=(20, 3)) + [0, 0, 6]
    out = biased_points(pc, np.full(20, 0.3), np.zeros(20), bias)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), bias.depth_scale * np.linalg.norm(pc, axis=1), rtol=1e-12)
    # one rigid rotation for all points: pairwise angles between rays are preserved
    cos_in = (pc @ pc.T) / np.outer(np.linalg.norm(pc, axis=1), np.linalg.norm(pc, axis=1))
    cos_out = (out @ out.T) / np.outer(np.linalg.norm(out, axis=1), np.linalg.norm(out, axis=1))
    np.testing.assert_allclose(cos_in, cos_out, atol=1e-12)


def test_default_config_has_no_systematic_error_and_draw_is_seeded():
    cfg = StereoConfig()
    bias = StereoBias.draw(5, cfg, np.random.default_rng(0))
    assert np.all(bias.centre_frac == 0) and bias.depth_scale == 1.0
    np.testing.assert_allclose(bias.R_cam_err, np.eye(3))
    real = StereoConfig(centre_error_frac=0.25, extrinsic_sigma_deg=0.15, depth_scale_sigma=0.003)
    a = StereoBias.draw(4000, real, np.random.default_rng(7))
    b = StereoBias.draw(4000, real, np.random.default_rng(7))
    np.testing.assert_array_equal(a.centre_frac, b.centre_frac)
    # zero mean (the pipeline's centre offset is calibrated), the configured spread
    assert abs(a.centre_frac.mean()) < 4 * 0.25 / np.sqrt(4000)
    assert 0.23 < a.centre_frac.std() < 0.27


def test_negative_settings_are_rejected_by_name():
    import pytest

    from sim.errors import SimError

    with pytest.raises(SimError, match="centre_error_frac=-0.1"):
        StereoBias.draw(3, StereoConfig(centre_error_frac=-0.1), np.random.default_rng(0))


def test_calibration_error_in_base_link_is_what_the_back_ends_estimate():
    from reloc.geometry import exp_so3
    from sim.sensors.stereo import StereoCamera, calibration_error_base

    cfg = StereoConfig(extrinsic_sigma_deg=0.3, depth_scale_sigma=0.01)
    bias = StereoBias.draw(3, cfg, np.random.default_rng(5))
    cam = StereoCamera.from_config(cfg)
    w, scale = calibration_error_base(bias, cam)
    assert scale == bias.depth_scale
    R_bc, t_bc = cam.T_base_cam[:3, :3], cam.T_base_cam[:3, 3]
    q_base = np.array([[4.0, 1.0, -0.8], [7.0, -2.0, -0.85], [2.0, 0.3, -0.9]])  # rocks ahead, on the ground
    pc = (q_base - t_bc) @ R_bc  # nominal camera frame
    z_base = biased_points(pc, np.full(3, 0.2), np.zeros(3), bias) @ R_bc.T + t_bc
    # z = t + s E (q - t) exactly, and the back-ends' model about the base origin to ~mm
    E = exp_so3(w)
    np.testing.assert_allclose(z_base, t_bc + scale * (q_base - t_bc) @ E.T, atol=1e-12)
    np.testing.assert_allclose(z_base, scale * q_base @ E.T, atol=0.003 + 2 * abs(scale - 1) * np.linalg.norm(t_bc))

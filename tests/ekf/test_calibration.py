"""Stereo calibration states: a known rotation and scale error of the rock measurements is
estimated, and the filter stays consistent where the uncalibrated one does not."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.calibration import CalibrationConfig
from reloc.errors import ConfigError
from reloc.geometry import exp_so3

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))
ROT = np.radians([0.0, 0.0, 1.5])  # a mounting error about base_link z
SCALE = 1.01


def _miscalibrated(run):
    """The same run seen through a camera with the rotation ROT and range scale SCALE."""
    E = exp_so3(ROT)
    frames = {}
    for k, obs in run.frames.items():
        frames[k] = dataclasses.replace(obs, xyz_base_m=SCALE * obs.xyz_base_m @ E.T,
                                        cov_base_m2=SCALE**2 * np.einsum("ij,njk,lk->nil", E, obs.cov_base_m2, E))
    return dataclasses.replace(run, frames=frames)


def _feed(ekf: EkfSlam, run) -> tuple[EkfSlam, np.ndarray]:
    err = []
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
        e = ekf.estimate()
        d = e.position_m[:2] - run.truth_p[k + 1, :2]
        err.append(float(d @ np.linalg.solve(e.cov[:2, :2], d)))
    return ekf, np.array(err)


@pytest.fixture(scope="module")
def run():
    return _miscalibrated(simulate(21, duration_s=90.0, n_rocks=260))


def test_rotation_and_scale_are_recovered_and_the_filter_stays_consistent(run):
    cal = CalibrationConfig(roll_pitch_sigma_deg=0.5, yaw_sigma_deg=3.0, scale_sigma=0.03)
    ekf, nees = _feed(EkfSlam(START, EkfConfig(calibration=cal)), run)
    c = ekf.calibration()
    assert abs(c["rotation_deg"][2] - np.degrees(ROT[2])) < 3 * c["rotation_sigma_deg"][2]
    assert c["rotation_sigma_deg"][2] < 0.5 * 3.0  # learnt, not just the prior
    assert abs(c["scale"] - SCALE) < 3 * c["scale_sigma"]
    assert ekf.stats().extra["calibration"] == c
    _, nees_plain = _feed(EkfSlam(START), run)
    inside = np.mean(nees < 11.83)  # chi2(2) 99.73 %: the 3-sigma ellipse
    assert inside > 0.95
    assert inside > np.mean(nees_plain < 11.83)


def test_off_by_default_and_bad_sigmas_rejected():
    offsets = 3 * len(EkfConfig().fix_gate.bias_sources)  # the fix sources' shared (x, y, yaw) errors
    ekf = EkfSlam(START)
    assert ekf.calibration() == {} and ekf.state_vector_size == 6 + 2 + offsets  # the pose, the yaw-rate bias, the slip
    assert EkfSlam(START, EkfConfig(calibration=CalibrationConfig(scale_sigma=0.01))).state_vector_size == 12 + offsets
    assert EkfSlam(START, EkfConfig(yaw_rate_bias_sigma_radps=0.0, slip_sigma=0.0)).state_vector_size == 6 + offsets
    with pytest.raises(ConfigError, match="yaw_sigma_deg must be >= 0"):
        CalibrationConfig(yaw_sigma_deg=-1.0)
    with pytest.raises(ConfigError, match="scale_sigma must be finite"):
        CalibrationConfig(scale_sigma=float("nan"))

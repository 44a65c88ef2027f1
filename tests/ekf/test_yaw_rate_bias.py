"""The IMU heading's drift rate (gyro bias about world z) as a filter state: landmarks' relative
rotations observe it, the filter learns it within its sigma and keeps its heading honest; without
the state the same drift leaves the heading outside 3 sigma."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import drift_heading, end_errors, simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate

BIAS = 1.5e-3  # rad/s: 5 deg in 60 s, so that one test minute shows it
START = PoseEstimate(0.0, np.eye(4), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))


@pytest.fixture(scope="module")
def drifting():
    return drift_heading(simulate(3, duration_s=60.0, frame_every=6, n_rocks=250), BIAS)


def _drive(run, cfg):
    ekf = EkfSlam(START, cfg)
    *_, err, sig = end_errors(ekf, run)
    return ekf, err, sig


def test_the_filter_learns_the_drift_and_keeps_its_heading(drifting):
    sigma_b = 3e-3
    ekf, err, sig = _drive(drifting, dataclasses.replace(EkfConfig(), yaw_rate_bias_sigma_radps=sigma_b))
    s = ekf._s
    b_sigma = float(np.sqrt(s.P[s.bias_col, s.bias_col]))
    assert abs(s.yaw_bias - BIAS) <= 3 * b_sigma and b_sigma < 0.5 * sigma_b  # learned, within its sigma
    assert abs(err) <= 3 * sig
    rep = ekf.stats().extra["yaw_rate_bias_deg_per_h"]
    assert rep["estimate"] == pytest.approx(np.degrees(s.yaw_bias) * 3600, abs=1e-3)


def test_without_the_state_the_heading_is_overconfident(drifting):
    _, err, sig = _drive(drifting, dataclasses.replace(EkfConfig(), yaw_rate_bias_sigma_radps=0.0))
    assert abs(err) > 3 * sig

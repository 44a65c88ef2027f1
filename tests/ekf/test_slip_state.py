"""The wheels' slip bias as a filter state: commands that overstate the driven distance by a
constant share are learned from the landmarks' motion over 50 s, and through the 40 s without
landmarks that follow the filter carries the rover on the corrected speed, inside its sigma; the
white slip terms alone cover the bias only by a wide sigma, and end more than twice as far off."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import end_errors, overstate_commands, simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate

SLIP = 0.06  # the rover drives 94 % of what it is commanded
SIGMA = 0.05  # the state's prior (EkfConfig.slip_sigma)
BLIND_FROM = 50 * 30  # step index (30 Hz): landmarks for 50 s, then 40 s blind
START = PoseEstimate(0.0, np.eye(4), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))


@pytest.fixture(scope="module")
def slipping():
    return overstate_commands(simulate(4, duration_s=90.0, frame_every=6, n_rocks=250), SLIP)


def _drive(run, cfg):
    ekf = EkfSlam(START, cfg)
    err, nees, *_ = end_errors(ekf, run, BLIND_FROM)  # then blind: the wheels alone carry the rover
    return ekf, err, nees


def test_the_filter_learns_the_slip_and_drives_blind_on_it(slipping):
    ekf, err, nees = _drive(slipping, dataclasses.replace(EkfConfig(), slip_sigma=SIGMA))
    s = ekf._s
    g_sigma = float(np.sqrt(s.P[s.slip_col, s.slip_col]))
    assert abs(s.slip - SLIP) <= 3 * g_sigma and g_sigma < 0.5 * SIGMA  # learned
    assert nees <= 11.8  # chi2(2 dof) 99.7 %
    assert ekf.stats().extra["slip"]["estimate"] == pytest.approx(s.slip, abs=1e-5)
    _, err_white, _ = _drive(slipping, dataclasses.replace(EkfConfig(), slip_sigma=0.0))
    assert err < 0.5 * err_white

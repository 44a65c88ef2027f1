"""``rock_cov_scale`` multiplies the detector's reported rock covariance, and nothing else."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.errors import ConfigError

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]))


def _feed(ekf: EkfSlam, run, cov_factor: float = 1.0) -> EkfSlam:
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            obs = run.frames[k]
            ekf.observe(dataclasses.replace(obs, cov_base_m2=obs.cov_base_m2 * cov_factor))
    return ekf


def test_scaled_filter_equals_the_filter_fed_scaled_covariances():
    run = simulate(3, duration_s=12.0, n_rocks=120)
    scaled = _feed(EkfSlam(START, dataclasses.replace(EkfConfig(), rock_cov_scale=4.0)), run)
    fed = _feed(EkfSlam(START), run, cov_factor=4.0)
    plain = _feed(EkfSlam(START), run)
    np.testing.assert_allclose(scaled.full_covariance(), fed.full_covariance(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(scaled.estimate().T_world_base, fed.estimate().T_world_base, atol=1e-12, rtol=0)
    # and it is not a no-op: less information per frame, a wider pose covariance
    assert np.trace(scaled.estimate().cov[:2, :2]) > 1.2 * np.trace(plain.estimate().cov[:2, :2])


@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_non_positive_scale_is_rejected_by_name(bad):
    with pytest.raises(ConfigError, match="rock_cov_scale"):
        EkfConfig(rock_cov_scale=bad)

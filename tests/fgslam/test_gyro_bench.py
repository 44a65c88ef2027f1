"""``python -m fgslam.bench.gyro``: the gyro monitor replayed over a simulated bag against the
truth: a gyro bias step is seen, confirmed and measured, and nothing is seen outside it."""

from __future__ import annotations

import pytest

from fgslam.bench.gyro import main
from tests.fgslam._yard_dir import write_yard_dir


@pytest.fixture(scope="module")
def bias_dir(tmp_path_factory):
    from sim import faults as F

    return write_yard_dir(tmp_path_factory.mktemp("gyrobench") / "bias", "my2020", 0, 6.0,
                          faults=F.FaultsConfig(imu_bias_step=F.ImuBiasStep(start_s=10.0, duration_s=40.0)))


def test_the_bias_step_is_seen_measured_and_nothing_else(bias_dir, tmp_path, capsys):
    res = main([str(bias_dir), "--out", str(tmp_path / "gyro.json")])
    assert (tmp_path / "gyro.json").is_file() and '"n_checks"' in capsys.readouterr().out
    assert res["n_detections"] == 1 and res["n_biased_checks"] >= 2
    assert res["false_alarms"] == 0 and res["missed"] <= 2  # the checks across the step's edges may miss
    # every biased check measured the bias over its interval (the step, 0.002 rad/s, or part of it
    # across the step's end) within 5e-4 rad/s, and no biased check lies outside the step
    est, true = res["estimated_bias_at_biased"], res["true_bias_at_biased"]
    assert all(abs(e - t) < 5e-4 for e, t in zip(est, true)) and max(true) > 0.0018
    assert min(true) > 3e-4
    assert 15.0 <= res["corrected_s"] <= 45.0
    assert res["heading_error_sigmas_p50_p90_p99"][1] < 3.0  # the scaled sigma is not optimistic

"""``python -m fgslam.bench.slip``: the slip monitor replayed over a simulated bag against the
truth: a stuck rover's slip is seen and confirmed, and nothing is seen where it drives freely."""

from __future__ import annotations

import pytest

from fgslam.bench.slip import main
from tests.fgslam._yard_dir import write_yard_dir


@pytest.fixture(scope="module")
def stuck_dir(tmp_path_factory):
    from sim import faults as F

    return write_yard_dir(tmp_path_factory.mktemp("slipbench") / "stuck", "my2020", 0, 6.0,
                          faults=F.FaultsConfig(stuck=F.Stuck(start_s=10.0, duration_s=20.0)))


def test_the_stuck_spell_is_seen_and_nothing_else(stuck_dir, tmp_path, capsys):
    res = main([str(stuck_dir), "--out", str(tmp_path / "slip.json")])
    assert (tmp_path / "slip.json").is_file() and '"n_checks"' in capsys.readouterr().out
    assert res["n_detections"] >= 1 and res["n_slipping_checks"] >= 5
    assert res["false_alarms"] == 0
    assert min(res["true_slip_at_slipping"]) > 0.3  # every slipping check is in the stuck spell (or its edge)
    assert 15.0 <= res["corrected_s"] <= 25.0
    assert len(res["visual_error_sigmas_p50_p90_p99"]) == 3

"""``python -m fgslam.bench.slip``: the slip monitor replayed over a simulated bag against the
truth: a stuck rover's slip is seen and confirmed, and nothing is seen where it drives freely."""

from __future__ import annotations

import dataclasses

import pytest

from fgslam.bench.slip import main


@pytest.fixture(scope="module")
def stuck_dir(tmp_path_factory):
    from fgslam.io.sim_dir import write_sim_dir
    from sim import faults as F
    from sim.config import SimConfig, TraverseConfig
    from sim.simulate import simulate

    cfg = SimConfig(world="my2020", seed=0)
    cfg = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse or TraverseConfig(), distance_m=6.0),
                              faults=F.FaultsConfig(stuck=F.Stuck(start_s=10.0, duration_s=20.0)))
    out = tmp_path_factory.mktemp("slipbench") / "stuck"
    write_sim_dir(simulate(cfg), out)
    return out


def test_the_stuck_spell_is_seen_and_nothing_else(stuck_dir, tmp_path, capsys):
    res = main([str(stuck_dir), "--out", str(tmp_path / "slip.json")])
    assert (tmp_path / "slip.json").is_file() and '"n_checks"' in capsys.readouterr().out
    assert res["n_detections"] >= 1 and res["n_slipping_checks"] >= 5
    assert res["false_alarms"] == 0
    assert min(res["true_slip_at_slipping"]) > 0.3  # every slipping check is in the stuck spell (or its edge)
    assert 15.0 <= res["corrected_s"] <= 25.0
    assert len(res["visual_error_sigmas_p50_p90_p99"]) == 3

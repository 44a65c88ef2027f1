"""``python -m fgslam.bench.consistency``: error and covariance growth of a back-end without
fixes over a simulated stream, per time bin, with the two-sided NEES verdict."""

from __future__ import annotations

import json

import pytest

from fgslam.bench.consistency import main
from tests.fgslam._yard_dir import write_yard_dir


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    return write_yard_dir(tmp_path_factory.mktemp("consbench") / "sim", "my2020", 1, 8.0)


def test_bins_cover_the_stretch_and_the_yaw_sigma_grows(sim_dir, tmp_path, capsys):
    out = tmp_path / "cons.json"
    res = main([str(sim_dir), "--backend", "ekf", "--duration-s", "60", "--bin-s", "15", "--out", str(out)])
    text = capsys.readouterr().out
    assert "| t s | distance m |" in text and res["consistency"]["position"]["verdict"] in text
    assert json.loads(out.read_text())["bins"] == res["bins"]
    bins = res["bins"]
    assert [b["t_s"] for b in bins] == [15.0, 30.0, 45.0, 60.0]
    assert all(b2["distance_m"] > b1["distance_m"] for b1, b2 in zip(bins, bins[1:]))  # the rover drives
    # no fixes: nothing observes the heading, so its sigma only grows (first-estimate Jacobians)
    assert all(b2["sigma_yaw_deg"] >= b1["sigma_yaw_deg"] - 1e-3 for b1, b2 in zip(bins, bins[1:]))
    assert res["ate_m"] < 0.5
    # the height beside the plane: its error inside 3 of its own sigmas on this short yard drive
    assert all(abs(b["err_z_m"]) <= 3.0 * b["sigma_z_m"] for b in bins) and "height error m" in text


def test_an_override_reaches_the_backend(sim_dir, capsys):
    res = main([str(sim_dir), "--backend", "ekf", "--duration-s", "30", "--bin-s", "15",
                "--set", "first_estimate_jacobians=false"])
    assert res["overrides"]["first_estimate_jacobians"] is False
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        main([str(sim_dir), "--duration-s", "30", "--set", "nonsense"])

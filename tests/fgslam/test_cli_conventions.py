"""CLI and API conventions (issue 16): --version, -v/-q, `fgslam config dump` (complete and
accepted back), every written config.yaml accepted by --config, --out refusing a directory fgslam
did not create unless --force, and the facade fgslam.simulate / run / compare."""

from __future__ import annotations

import json
import logging

import pytest
import yaml
from _synth_stream import make_stream, write_input_dir

import fgslam
from fgslam.cli import main


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    return write_input_dir(tmp_path_factory.mktemp("conv") / "synth", make_stream(seed=11, duration_s=30.0))


def _ate(out) -> float:
    return json.loads((out / "metrics.json").read_text())["ate"]["rmse"]


def test_version_and_log_levels(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"fgslam {fgslam.__version__}"
    root = logging.getLogger()
    level = root.level
    try:
        assert main(["-q", "config", "dump"]) == 0 and root.level == logging.ERROR
        assert main(["-v", "config", "dump"]) == 0 and root.level == logging.INFO
        assert main(["-vv", "config", "dump"]) == 0 and root.level == logging.DEBUG
        assert main(["-v", "-q", "config", "dump"]) == 2
    finally:
        root.setLevel(level)


def test_config_dump_is_complete_and_accepted_back(synth_dir, tmp_path, capsys):
    from fgslam.backends.registry import BACKEND_NAMES
    from fgslam.cli.cmd_sim import load_sim_config
    from sim.config import SimConfig

    assert main(["config", "dump", "--out", str(tmp_path / "run.yaml")]) == 0
    dumped = yaml.safe_load((tmp_path / "run.yaml").read_text())
    assert set(dumped["backend_overrides"]) == set(BACKEND_NAMES)
    assert {"runner", "relocalizer", "topics", "images", "rpe_delta_m", "workers"} <= set(dumped)
    base = ["run", str(synth_dir), "--backend", "ekf"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    assert main([*base, "--out", str(tmp_path / "b"), "--config", str(tmp_path / "run.yaml")]) == 0
    a, b = (yaml.safe_load((tmp_path / d / "config.yaml").read_text()) for d in "ab")
    assert a == b and _ate(tmp_path / "a") == _ate(tmp_path / "b")
    # a run's config.yaml is accepted back by run and by compare
    assert main([*base, "--out", str(tmp_path / "c"), "--config", str(tmp_path / "a" / "config.yaml")]) == 0
    assert _ate(tmp_path / "c") == _ate(tmp_path / "a")
    # the simulator's dump gives the defaults back
    assert main(["config", "dump", "sim", "--out", str(tmp_path / "sim.yaml")]) == 0
    assert load_sim_config(None, None, None, tmp_path / "sim.yaml") == load_sim_config(None, None, None, None)
    assert load_sim_config(None, None, None, None).world == SimConfig().world
    assert main(["config", "dump", "lidar"]) == 2


def test_out_refuses_a_directory_it_did_not_create_unless_forced(synth_dir, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    args = ["run", str(synth_dir), "--backend", "dr", "--no-reloc", "--out", str(mine)]
    assert main(args) == 2
    assert "--force" in capsys.readouterr().err and not (mine / "metrics.json").exists()
    assert main([*args, "--force"]) == 0
    assert (mine / "notes.txt").read_text() == "keep" and (mine / "dr.tum").exists()
    assert main(args) == 0  # now it holds fgslam's manifest: a rerun replaces its own files


def test_the_facade_in_three_lines(synth_dir, tmp_path):
    out = fgslam.run(synth_dir, backend="ekf", out=tmp_path / "r", config={"rpe_delta_m": 2.0})
    assert out.key == "ekf_reloc" and out.metrics["ate"]["rmse"] == _ate(tmp_path / "r")
    assert out.used["rpe_delta_m"] == 2.0
    table = fgslam.compare([synth_dir], config={"workers": 1, "backends": ["ekf"], "reference_backend": "ekf"})
    assert table[0]["runs"]["ekf_reloc"]["ate"]["rmse"] == pytest.approx(out.metrics["ate"]["rmse"], rel=1e-9)
    sim_dir = fgslam.simulate("my2022", tmp_path / "sim", seed=1, distance_m=3)
    assert (sim_dir / "bag" / "metadata.yaml").is_file() and (sim_dir / "catalog.csv").is_file()
    with pytest.raises(fgslam.FgslamError, match="already holds"):
        fgslam.simulate("my2022", tmp_path / "sim", seed=1, distance_m=3)

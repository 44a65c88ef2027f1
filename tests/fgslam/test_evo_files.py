"""evo conventions (issue 16): `fgslam run` and `fgslam compare` write each variant's trajectory
as <variant>.tum beside ground_truth.tum, and evo's own command-line tools, run on those files,
give fgslam's figures: `evo_ape tum` its ATE, `evo_rpe tum --delta D --delta_unit m` its RPE."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml
from _synth_stream import make_stream, write_input_dir

from fgslam.cli import main

EVO_BIN = Path(sys.executable).parent


def _evo(tool: str, gt: Path, est: Path, tmp: Path, *args: str) -> dict:
    """evo's statistics of ``tool`` (evo_ape / evo_rpe) from the results file it saves."""
    res = tmp / f"{tool}_{est.stem}.zip"
    r = subprocess.run([str(EVO_BIN / tool), "tum", str(gt), str(est), "--no_warnings", "--save_results", str(res),
                        *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    with zipfile.ZipFile(res) as z:
        return json.loads(z.read("stats.json"))


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    return write_input_dir(tmp_path_factory.mktemp("evo") / "synth", make_stream(seed=5, duration_s=60.0))


@pytest.mark.parametrize("long", [False, True], ids=["yard", "long traverse"])
def test_evo_ape_and_rpe_on_fgslams_files_equal_its_figures(synth_dir, tmp_path, long):
    """Also as a long traverse (one pose a second recorded, fgslam.long_traverse): evo pairs stamps
    without interpolating, so ground_truth.tum keeps every truth pose."""
    cfg = {"rpe_delta_m": 2.0, **({"long_traverse": {"min_duration_s": 30.0}} if long else {})}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    assert main(["run", str(synth_dir), "--backend", "ekf", "--out", str(out), "--config", str(tmp_path / "c.yaml")]) == 0
    assert {p.name for p in out.glob("*.tum")} == {"ekf_reloc.tum", "ground_truth.tum"}
    met = json.loads((out / "metrics.json").read_text())
    ape = _evo("evo_ape", out / "ground_truth.tum", out / "ekf_reloc.tum", tmp_path)
    rpe = _evo("evo_rpe", out / "ground_truth.tum", out / "ekf_reloc.tum", tmp_path, "--delta", "2", "--delta_unit", "m")
    assert met["ate"]["rmse"] > 0.01 and met["rpe"]["rmse"] > 0.001  # not a trivial agreement
    for ours, evo in ((met["ate"], ape), (met["rpe"], rpe)):
        assert ours["rmse"] == pytest.approx(evo["rmse"], rel=1e-6)
        assert ours["max"] == pytest.approx(evo["max"], rel=1e-6)
        assert ours["mean"] == pytest.approx(evo["mean"], rel=1e-6)


def test_a_comparison_writes_every_variant_by_name(synth_dir, tmp_path):
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"workers": 1, "backends": ["ekf"], "reference_backend": "ekf"}))
    out = tmp_path / "cmp"
    assert main(["compare", str(synth_dir), "--out", str(out), "--no-rrd", "--config", str(tmp_path / "c.yaml")]) == 0
    names = {p.name for p in (out / "synth").glob("*.tum")}
    assert names == {"ekf.tum", "ekf_reloc.tum", "dead_reckoning.tum", "ground_truth.tum"}
    runs = json.loads((out / "results.json").read_text())["worlds"][0]["runs"]
    for key in ("ekf", "ekf_reloc"):
        ape = _evo("evo_ape", out / "synth" / "ground_truth.tum", out / "synth" / f"{key}.tum", tmp_path)
        assert runs[key]["ate"]["rmse"] == pytest.approx(ape["rmse"], rel=1e-6)

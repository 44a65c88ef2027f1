"""Comparison outputs on a synthetic traverse, CLI errors, and one seeded end-to-end CLI run."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from _synth_stream import NearestNeighbourMatcher, make_stream

from fgslam import metrics as M
from fgslam.compare import CompareConfig, CompareError, compare_world
from fgslam.outputs import write_comparison
from fgslam.relocalizer import Relocalizer
from fgslam.report import markdown_table


def _compare(workers: int):
    inputs = make_stream(seed=7, duration_s=40.0)
    cfg = CompareConfig(backends=("dr",), reference_backend="dr", backend_overrides={"dr": {"use_fixes": True}},
                        workers=workers)
    reloc = Relocalizer(inputs.catalog, cfg.relocalizer, matcher=NearestNeighbourMatcher(inputs.catalog.xy_m))
    return cfg, compare_world(inputs, cfg, relocalizers=[reloc])


@pytest.fixture(scope="module")
def compared():
    return _compare(workers=1)


def test_every_variant_receives_the_same_fixes(compared):
    _, wc = compared
    fixes = [a.fix for a in wc.attempts if a.fix is not None]
    assert fixes, "the reference pass produced no fix"
    for key, run in wc.runs.items():
        if key.endswith("_reloc"):
            assert [o.fix for o in run.outcomes] == [f for f in fixes if f.t_recv <= run.t_end]
        else:
            assert run.outcomes == []


@pytest.mark.parametrize("workers", [2, None])  # None: every pass at once (the default)
def test_forked_workers_give_identical_results(compared, workers):
    _, wc1 = compared
    _, wc2 = _compare(workers=workers)
    for key in wc1.runs:
        assert np.array_equal(wc1.runs[key].final.T_world_base, wc2.runs[key].final.T_world_base)
    assert wc1.metrics["runs"]["dr_reloc"]["ate"] == wc2.metrics["runs"]["dr_reloc"]["ate"]


def test_outputs_table_json_plots(tmp_path, compared):
    cfg, wc = compared
    files = write_comparison(tmp_path, [wc], cfg, rrd=False)
    names = {f.name for f in files}
    assert {"table.md", "results.json", "config.yaml", f"{wc.inputs.name}_xy.png",
            f"{wc.inputs.name}_errors.png", f"{wc.inputs.name}_fix_errors.png"} <= names
    res = json.loads((tmp_path / "results.json").read_text())
    world = res["worlds"][0]
    m = world["runs"]
    # the table and the JSON hold the measured values
    assert m["dr_reloc"]["ate"]["rmse"] < m["dr"]["ate"]["rmse"]
    assert m["dr_reloc"]["fixes"]["fixes"] == len([a for a in wc.attempts if a.fix is not None])
    assert world["distance_m"] == pytest.approx(wc.metrics["distance_m"])
    table = (tmp_path / "table.md").read_text()
    assert table == markdown_table([wc.metrics])
    assert f"| Dead reckoning + reloc ATE [m] | {m['dr_reloc']['ate']['rmse']:.3f} |" in table
    # the ATE's planar and height parts: their squares sum to the 3D ATE's
    for run in m.values():
        if "ate" in run:
            assert run["ate_planar"]["rmse"] ** 2 + run["height_error"]["rmse"] ** 2 == pytest.approx(
                run["ate"]["rmse"] ** 2)
    p, h = m["dr_reloc"]["ate_planar"]["rmse"], m["dr_reloc"]["height_error"]["rmse"]
    assert f"| Dead reckoning + reloc ATE planar / height RMSE [m] | {p:.3f} / {h:.3f} |" in table
    for png in ("xy", "errors", "fix_errors", "error_vs_distance", "xy_error"):
        assert (tmp_path / f"{wc.inputs.name}_{png}.png").read_bytes()[:4] == b"\x89PNG"
    # drift: the final error over the distance, as the error-against-distance figure states it
    dist, err = M.error_along(wc.runs["dr"].final, wc.gt)
    assert m["dr"]["drift_pct"] == pytest.approx(100 * err[-1] / dist[-1])
    assert f"| Dead reckoning drift [% of distance] | {m['dr']['drift_pct']:.2f} |" in table


def test_bad_config_is_rejected():
    inputs = make_stream(seed=1, duration_s=5.0)
    with pytest.raises(CompareError, match="reference_backend"):
        compare_world(inputs, CompareConfig(backends=("ekf",), reference_backend="isam2"))


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fgslam", *args], check=False, capture_output=True, text=True, cwd=cwd)


def test_cli_reports_missing_and_malformed_inputs(tmp_path):
    r = _cli("compare", str(tmp_path / "nope"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "not a directory" in r.stderr
    (tmp_path / "d").mkdir()
    r = _cli("run", str(tmp_path / "d"), "--backend", "isam2", "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "missing bag" in r.stderr
    r = _cli("run", "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "--bag" in r.stderr
    (tmp_path / "bad.yaml").write_text("relocalizer: {period_s: -1}\n")
    r = _cli("run", str(tmp_path / "d"), "--out", str(tmp_path / "o"), "--config", str(tmp_path / "bad.yaml"))
    assert r.returncode == 2 and "period_s" in r.stderr
    (tmp_path / "typo.yaml").write_text("relocaliser: {}\n")
    r = _cli("run", str(tmp_path / "d"), "--out", str(tmp_path / "o"), "--config", str(tmp_path / "typo.yaml"))
    assert r.returncode == 2 and "relocaliser" in r.stderr


@pytest.mark.slow
def test_cli_sim_run_compare_end_to_end(tmp_path):
    """`fgslam sim` -> `fgslam run` (files read back by evo) -> `fgslam compare` on a short seeded traverse."""
    from evo.tools import file_interface
    from rerun.chunk import RrdReader

    sim_dir = tmp_path / "sim"
    r = _cli("sim", "--world", "my2022", "--seed", "3", "--distance-m", "3", "--out", str(sim_dir))
    assert r.returncode == 0, r.stderr[-3000:]
    out = tmp_path / "run"
    r = _cli("run", str(sim_dir), "--backend", "isam2", "--out", str(out), "--rrd", str(out / "run.rrd"))
    assert r.returncode == 0, r.stderr[-3000:]
    traj = file_interface.read_tum_trajectory_file(str(out / "isam2_reloc.tum"))
    met = json.loads((out / "metrics.json").read_text())
    assert traj.num_poses == met["ate"]["n"]
    assert met["ate"]["rmse"] < 0.5
    assert (out / "fixes.csv").read_text().startswith("t_meas,t_recv,x_m,y_m,yaw_rad")
    import yaml

    used = yaml.safe_load((out / "config.yaml").read_text())
    assert used["backend"] == "isam2" and used["relocalization"] is True and "period_s" in used["relocalizer"]
    assert any(c.entity_path.endswith("/isam2_reloc/path") for c in RrdReader(out / "run.rrd").stream())
    cmp_out = tmp_path / "cmp"
    r = _cli("compare", str(sim_dir), "--out", str(cmp_out))
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((cmp_out / "results.json").read_text())
    runs = res["worlds"][0]["runs"]
    assert set(runs) == {"ekf", "ekf_reloc", "isam2", "isam2_reloc", "dead_reckoning"}
    # the compare's iSAM2 + reloc run is the same computation as `fgslam run` above
    assert runs["isam2_reloc"]["ate"]["rmse"] == pytest.approx(met["ate"]["rmse"], rel=1e-9)
    assert "| Distance [m] |" in r.stdout and (cmp_out / "compare.rrd").exists()
    assert (cmp_out / f"{sim_dir.name}_xy.png").exists()
    # every config the commands saved is accepted back by --config, and means what was used
    from fgslam.cli.cmd_run import load_config
    from fgslam.cli.cmd_sim import load_sim_config
    from fgslam.compare import CompareConfig
    from reloc.config import config_to_dict

    back = load_config(out / "config.yaml")
    assert config_to_dict(back.runner) == used["runner"] and config_to_dict(back.relocalizer) == used["relocalizer"]
    from fgslam.backends.registry import backend_config

    assert backend_config("isam2", back.backend_overrides.get("isam2")) == backend_config("isam2", used["backend_config"])
    from fgslam.compare import resolved_compare_config

    assert resolved_compare_config(load_config(cmp_out / "config.yaml")) == resolved_compare_config(CompareConfig())
    world = yaml.safe_load((sim_dir / "world.yaml").read_text())
    assert config_to_dict(load_sim_config(None, None, None, sim_dir / "world.yaml")) == world["config"]
    for d in (sim_dir, out, cmp_out):
        assert json.loads((d / "manifest.json").read_text())["status"] == "complete"


def test_draw_start_moves_every_pass_start_by_the_seeded_draw():
    """``draw_start``: every pass starts from the draw of the start's prior seeded with the
    simulator's seed (the dead-reckoning pass shows it: its first pose is the start); inputs
    without a seed are refused by name."""
    from fgslam.inputs import start_drawn_from_prior

    inputs = make_stream(seed=7, duration_s=10.0)
    cfg = CompareConfig(backends=("dr",), reference_backend="dr", workers=1, draw_start=True)
    reloc = Relocalizer(inputs.catalog, cfg.relocalizer, matcher=NearestNeighbourMatcher(inputs.catalog.xy_m))
    del inputs.source["seed"]
    with pytest.raises(CompareError, match="draw_start needs the simulator's seed"):
        compare_world(inputs, cfg, relocalizers=[reloc])
    inputs.source["seed"] = 4
    wc = compare_world(inputs, cfg, relocalizers=[reloc])
    drawn = start_drawn_from_prior(inputs.initial, 4).T_world_base
    first = wc.runs["dr"].final.T_world_base[0]
    assert np.linalg.norm(drawn[:3, 3] - inputs.initial.T_world_base[:3, 3]) > 1e-4
    np.testing.assert_allclose(first[:3, 3], drawn[:3, 3], atol=1e-9)
    np.testing.assert_allclose(first[:3, :3], drawn[:3, :3], atol=1e-9)


@pytest.mark.parametrize("given", [{}, {"isam2": {"fixed_lag_s": 0.0}, "ekf": {"keep_seen_s": 0.5}}])
def test_a_saved_comparison_config_given_back_runs_every_world_as_before(tmp_path, given):
    """The saved config writes every back-end value out but those the long-traverse rule decides
    per world: given back, a kilometre world still gets iSAM2's fixed-lag window and the EKF's
    forgetting (a written-out ``fixed_lag_s: 0`` made it a full-history smoother), a yard none,
    and what the user set explicitly stays set."""
    import yaml

    from fgslam.backends.registry import backend_config, resolved_config
    from fgslam.cli.cmd_run import load_config
    from fgslam.compare import CompareConfig, resolved_compare_config
    from fgslam.long_traverse import backend_overrides_for

    cfg = CompareConfig(backend_overrides=given)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({"config": resolved_compare_config(cfg)}, sort_keys=False))
    back = load_config(path)
    lt = cfg.long_traverse
    for span in (600.0, 2 * lt.min_duration_s):
        for name in ("isam2", "ekf"):
            before = resolved_config(name, backend_overrides_for(name, cfg.backend_overrides.get(name), span, lt))
            after = resolved_config(name, backend_overrides_for(name, back.backend_overrides.get(name), span, lt))
            assert after == before, (name, span)
    long_isam2 = backend_config("isam2", backend_overrides_for("isam2", back.backend_overrides.get("isam2"),
                                                                2 * lt.min_duration_s, lt))
    assert long_isam2.fixed_lag_s == (0.0 if given else lt.isam2_fixed_lag_s)

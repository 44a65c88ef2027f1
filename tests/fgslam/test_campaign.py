"""Monte Carlo campaigns: spec parsing, aggregation against hand-computed numbers, the JSONL store,
and seeded campaigns on Dask (1 vs 2 workers identical, a failing task reported, resume)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fgslam.campaign import (
    CampaignError,
    CampaignSpec,
    ResultStore,
    aggregate,
    expand,
    parse_overrides,
    parse_seeds,
    read_records,
    require_dask,
    run_campaign,
    summary_markdown,
    variants_from_sweeps,
    write_summary,
)

BAD_WORLD = "/nonexistent_world_dir"
SHORT = {"sim.traverse.distance_m": 5.0}  # a 5 m traverse: one task simulates and compares in ~3 s
SPEC = CampaignSpec(worlds=("my2022", BAD_WORLD), seeds=(0, 1), overrides=SHORT)


# ---- spec ---------------------------------------------------------------------------------------

def test_seeds_parse_ranges_and_lists():
    assert parse_seeds("0-3,7") == (0, 1, 2, 3, 7)
    assert parse_seeds("5") == (5,)
    assert parse_seeds("3,1-2,2") == (1, 2, 3)
    with pytest.raises(CampaignError, match="'x'"):
        parse_seeds("0,x")
    with pytest.raises(CampaignError, match="ends before it starts"):
        parse_seeds("5-2")


def test_overrides_find_their_config_and_bad_keys_are_named():
    ov = parse_overrides(["relocalizer.period_s=5", "traverse.distance_m=20", "sim.sensors.imu.rate_hz=30",
                          "relocalizer.latency=measured"])
    assert ov == {"compare.relocalizer.period_s": 5, "sim.traverse.distance_m": 20,
                  "sim.sensors.imu.rate_hz": 30, "compare.relocalizer.latency": "measured"}
    # YAML 1.1 reads an exponent without a dot as a string; a number is meant
    assert parse_overrides(["sim.sensors.imu.gyro_bias_walk_radps_rsqrt_s=4e-9"]) == {
        "sim.sensors.imu.gyro_bias_walk_radps_rsqrt_s": 4e-9}
    assert parse_overrides(["relocalizer.latency=measured"]) == {"compare.relocalizer.latency": "measured"}
    with pytest.raises(CampaignError, match="'relocaliser'"):
        parse_overrides(["relocaliser.period_s=5"])
    with pytest.raises(CampaignError, match="--seeds"):
        parse_overrides(["seed=3"])
    with pytest.raises(CampaignError, match="key=value"):
        parse_overrides(["relocalizer.period_s"])
    # unknown nested keys and out-of-range values are caught before any work, naming the variant
    with pytest.raises(CampaignError, match="period"):
        expand(CampaignSpec(("cnes",), (0,), parse_overrides(["relocalizer.period=3"])))
    with pytest.raises(CampaignError, match="period_s must be > 0"):
        expand(CampaignSpec(("cnes",), (0,), parse_overrides(["relocalizer.period_s=-1"])))
    with pytest.raises(CampaignError, match="distance_m"):
        expand(CampaignSpec(("cnes",), (0,), parse_overrides(["traverse.distance_m=-1"])))


def test_sweeps_expand_to_every_combination_of_tasks():
    variants = variants_from_sweeps(["relocalizer.period_s=2,5", "sensors.stereo.sigma_pixel_px=1.0,[2]"])
    assert list(variants) == [
        "relocalizer.period_s=2 sensors.stereo.sigma_pixel_px=1.0", "relocalizer.period_s=2 sensors.stereo.sigma_pixel_px=[2]",
        "relocalizer.period_s=5 sensors.stereo.sigma_pixel_px=1.0", "relocalizer.period_s=5 sensors.stereo.sigma_pixel_px=[2]",
    ]
    assert variants["relocalizer.period_s=5 sensors.stereo.sigma_pixel_px=[2]"] == {
        "compare.relocalizer.period_s": 5, "sim.sensors.stereo.sigma_pixel_px": [2]}
    spec = CampaignSpec(("cnes", "my2020"), (0, 1, 2), SHORT, variants_from_sweeps(["relocalizer.period_s=2,5"]))
    tasks = expand(spec)
    assert len(tasks) == 2 * 3 * 2
    assert len({t["key"] for t in tasks}) == len(tasks)
    t = next(t for t in tasks if t["key"] == "my2020/relocalizer.period_s=5/seed2")
    assert t["overrides"] == {"sim.traverse.distance_m": 5.0, "compare.relocalizer.period_s": 5}
    # the same overrides hash the same; a different value hashes differently
    by_var = {t["variant"]: t["config_hash"] for t in tasks}
    assert len(set(by_var.values())) == 2
    assert variants_from_sweeps([]) == {"base": {}}


def test_a_kilometre_preset_takes_its_own_config_and_its_backend_yaml_under_the_overrides():
    """On a kilometre preset the simulator overrides lie on that preset's config (as `fgslam sim`
    gives it), and the task's comparison overrides on the run's backend.yaml, merged key by key: a
    window set for the smoother keeps the calibration its sensors need."""
    from fgslam.campaign.spec import build_configs
    from sim.tiled.presets import backend_calibration, preset_config, relocalizer_calibration

    over = parse_overrides(["traverse.distance_m=40", "backend_overrides.isam2.fixed_lag_s=60"])
    preset = preset_config("rocky-1km", 2)
    base = {"backend_overrides": backend_calibration(preset), "relocalizer": relocalizer_calibration(preset)}
    sim_cfg, cmp_cfg = build_configs(over, "rocky-1km", 2, compare_base=base)
    assert sim_cfg.traverse.distance_m == 40.0
    assert sim_cfg.sensors == preset.sensors and sim_cfg.sensors.cmd.target_drift_pct is None  # not the yard's
    isam2 = cmp_cfg.backend_overrides["isam2"]
    assert isam2["fixed_lag_s"] == 60.0 and isam2["calibration"] == base["backend_overrides"]["isam2"]["calibration"]
    assert cmp_cfg.backend_overrides["ekf"] == base["backend_overrides"]["ekf"]
    assert cmp_cfg.relocalizer.matcher["sigma_m"] == base["relocalizer"]["matcher"]["sigma_m"]
    assert base["backend_overrides"]["isam2"].get("fixed_lag_s") is None  # the base is not changed
    # a yard keeps the yard defaults
    yard, _ = build_configs(over)
    assert yard.sensors.cmd.target_drift_pct is not None
    # what a kilometre preset refuses is refused at expansion, naming the world
    with pytest.raises(CampaignError, match="rocky-1km"):
        expand(CampaignSpec(("rocky-1km",), (0,), parse_overrides(["faults.camera_blackout={start_s: 5, duration_s: 5}"])))
    # a spec built in code with a key lacking its prefix finds it; an unknown key is named
    _, cfg = build_configs({"relocalizer.period_s": 7.0})
    assert cfg.relocalizer.period_s == 7.0
    with pytest.raises(CampaignError, match="'traverse_m'"):
        expand(CampaignSpec(("cnes",), (0,), {"traverse_m.distance_m": 5.0}))


def test_task_directories_of_dead_processes_are_swept_and_no_other(tmp_path):
    """A worker killed in a task leaves its bag behind; the next task on the machine removes the
    directories whose process is gone, and nothing else."""
    from fgslam.campaign.task import TASK_DIR_PREFIX, sweep_task_dirs

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], check=True,
                          capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    left = tmp_path / f"{TASK_DIR_PREFIX}{dead_pid}-x1y2"
    (left / "sim" / "bag").mkdir(parents=True)
    (left / "sim" / "bag" / "bag.mcap").write_bytes(b"0" * 1000)
    kept = [tmp_path / f"{TASK_DIR_PREFIX}{os.getpid()}-mine", tmp_path / f"{TASK_DIR_PREFIX}{os.getppid()}-alive",
            tmp_path / f"{TASK_DIR_PREFIX}abc", tmp_path / "other-123-dir"]
    for d in kept:
        d.mkdir()
    assert sweep_task_dirs(tmp_path) == [left]
    assert not left.exists() and all(d.is_dir() for d in kept)


@pytest.mark.slow
def test_a_kilometre_task_streams_its_preset_and_leaves_no_files(tmp_path, monkeypatch):
    """A kilometre task simulates its preset into a temporary bag on the worker, compares the four
    variants on it streamed, and removes the bag; its record carries drift, update p99 and RSS."""
    import tempfile

    from fgslam.campaign import run_task

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    task = expand(CampaignSpec(("rocky-1km",), (2,), {"sim.traverse.distance_m": 4.0}))[0]
    rec = run_task(task)
    assert rec["status"] == "ok", rec.get("traceback")
    res = rec["result"]
    assert res["distance_m"] == pytest.approx(4.0, abs=1.0)
    assert set(res["runs"]) == {"ekf", "ekf_reloc", "isam2", "isam2_reloc", "dead_reckoning"}
    for key in ("ekf", "ekf_reloc", "isam2", "isam2_reloc"):
        run = res["runs"][key]
        assert 0.0 < run["ate_rmse_m"] < 0.1 and run["drift_pct"] is not None
        assert run["n_landmarks"] > 10 and run["nees_position"]["n_eff"] > 1
        assert rec["runtime"]["runs_update_p99_ms"][key] > 0
        assert 0 < rec["runtime"]["runs_frame_cpu_p99_ms"][key] < 1e3
    assert res["runs"]["dead_reckoning"]["ate_rmse_m"] > 2 * res["runs"]["ekf"]["ate_rmse_m"]
    assert res["fixes"]["attempts"] > 0
    assert rec["runtime"]["peak_rss_mb"] > 100
    assert list(tmp_path.iterdir()) == []  # the bag and catalogs went with the task
    assert len(json.dumps(rec)) < 10_000


# ---- aggregation ----------------------------------------------------------------------------------

def _record(world, seed, ate_isam2_reloc, fix_err, rtf, status="ok"):
    rec = {"key": f"{world}/base/seed{seed}", "world": world, "variant": "base", "seed": seed,
           "config_hash": "h", "overrides": {}, "status": status, "runtime": {"real_time_factor": rtf, "pid": 1}}
    if status == "ok":
        rec["result"] = {
            "runs": {"isam2_reloc": {"ate_rmse_m": ate_isam2_reloc, "improvement_over_baseline_pct": 100 - 100 * ate_isam2_reloc,
                                     "inside_3sigma": 1.0}},
            "fixes": {"rate_hz": 0.25, "position_error_median_m": fix_err, "fixes": 10},
        }
    else:
        rec["error"] = "SimError: boom | bad"
    return rec


def test_aggregation_matches_hand_computed_statistics(tmp_path):
    records = [_record("w", 0, 0.1, 0.05, 40.0), _record("w", 1, 0.2, None, 60.0), _record("w", 2, 0.4, 0.15, 50.0),
               _record("w", 3, 0.3, 0.10, 70.0), _record("w", 4, None, None, None, status="error"),
               _record("v", 0, 0.5, 0.2, 10.0)]
    s = aggregate(records)
    assert (s["n_tasks"], s["n_ok"], s["n_failed"]) == (6, 5, 1)
    g = {x["world"]: x for x in s["groups"]}["w"]
    assert g["seeds_ok"] == [0, 1, 2, 3] and g["seeds_failed"] == [4]
    ate = g["metrics"]["runs.isam2_reloc.ate_rmse_m"]
    # by hand: mean (0.1 + 0.2 + 0.4 + 0.3) / 4 = 0.25; median of 0.1 0.2 0.3 0.4 = 0.25;
    # p90 (linear): rank 0.9 * 3 = 2.7 -> 0.3 + 0.7 * (0.4 - 0.3) = 0.37
    assert ate == pytest.approx({"mean": 0.25, "median": 0.25, "p90": 0.37, "n": 4})
    imp = g["metrics"]["runs.isam2_reloc.improvement_over_baseline_pct"]
    assert imp["mean"] == pytest.approx(75.0) and imp["p90"] == pytest.approx(87.0)  # 60 70 80 90: 80 + 0.7 * 10
    fix = g["metrics"]["fixes.position_error_median_m"]  # the seed without fixes is left out
    assert fix == pytest.approx({"mean": 0.10, "median": 0.10, "p90": 0.14, "n": 3})  # 0.05 0.10 0.15: 0.1 + 0.8 * 0.05
    rtf = g["metrics"]["runtime.real_time_factor"]
    assert rtf == pytest.approx({"mean": 55.0, "median": 55.0, "p90": 67.0, "n": 4})
    assert "runtime.pid" not in g["metrics"]
    assert s["failures"] == [{"key": "w/base/seed4", "world": "w", "variant": "base", "seed": 4,
                              "error": "SimError: boom | bad"}]

    md_path, js_path = write_summary(tmp_path, records)
    md = md_path.read_text()
    assert md == summary_markdown(s, records)
    assert "| iSAM2 + reloc ATE [m] | 0.250 | 0.250 | 0.370 | 4 |" in md
    assert "| Fix median position error [m] | 0.100 | 0.100 | 0.140 | 3 |" in md
    assert "| iSAM2 + reloc inside 3-sigma [%] | 100.0 | 100.0 | 100.0 | 4 |" in md
    assert "Seeds ok: 0-3; failed: 4." in md
    assert "| w/base/seed4 | SimError: boom \\| bad |" in md
    assert "| w | base | 1 | - | - | - | 0.200 | 10 | 0.250 | - | 60.000 |" in md

    def no_nan(text):
        raise AssertionError(f"non-standard JSON constant {text}")

    js = json.loads(js_path.read_text(), parse_constant=no_nan)
    assert js["groups"][0]["metrics"]["runs.isam2_reloc.ate_rmse_m"]["p90"] == pytest.approx(0.37)


# ---- results file ---------------------------------------------------------------------------------

def test_store_survives_a_torn_line_and_keeps_the_latest_record(tmp_path):
    store = ResultStore(tmp_path)
    a = _record("w", 0, 0.1, 0.05, 40.0, status="error")
    store.append(a)
    with store.path.open("a") as fh:  # an interrupted write
        fh.write('{"key": "w/base/seed1", "stat')
    b = _record("w", 0, 0.1, 0.05, 40.0)
    store.append({**b, "runtime": {"real_time_factor": float("nan")}})  # NaN becomes null: strict JSON
    recs = read_records(store.path)
    assert [r["status"] for r in recs] == ["error", "ok"]
    assert recs[1]["runtime"]["real_time_factor"] is None
    assert store.done() == {("w/base/seed0", "h")}
    lines = store.path.read_text().splitlines()
    assert len(lines) == 3 and json.loads(lines[2])["status"] == "ok"


def test_missing_dask_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    with pytest.raises(CampaignError, match=r"fgslam\[dask\]"):
        require_dask()


def test_the_command_line_does_not_import_dask():
    code = "import sys, fgslam.cli, fgslam.campaign; sys.exit(any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


# ---- seeded campaigns on Dask -------------------------------------------------------------------

@pytest.fixture(scope="module")
def one_worker(tmp_path_factory):
    """SPEC on a local cluster of one worker: 2 simulated tasks, 2 failing ones."""
    out = tmp_path_factory.mktemp("campaign1")
    return out, run_campaign(SPEC, out, n_workers=1)


@pytest.fixture(scope="module")
def cluster():
    """An existing two-worker cluster, reached by its scheduler address like a remote one."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as c:
        yield c.scheduler_address


def _by_key(records):
    return {r["key"]: r for r in records}


@pytest.mark.slow
def test_campaign_reports_failures_and_writes_small_records(one_worker):
    out, run = one_worker
    assert (run.computed, run.skipped) == (4, 0)
    recs = _by_key(run.records)
    assert set(recs) == {"my2022/base/seed0", "my2022/base/seed1", f"{BAD_WORLD}/base/seed0", f"{BAD_WORLD}/base/seed1"}
    for seed in (0, 1):
        bad = recs[f"{BAD_WORLD}/base/seed{seed}"]
        assert bad["status"] == "error" and BAD_WORLD in bad["error"] and "SimError" in bad["error"]
        ok = recs[f"my2022/base/seed{seed}"]["result"]
        assert recs[f"my2022/base/seed{seed}"]["status"] == "ok"
        assert ok["distance_m"] == pytest.approx(5.0, abs=0.5)
        assert set(ok["runs"]) == {"ekf", "ekf_reloc", "isam2", "isam2_reloc", "dead_reckoning"}
        for key in ("ekf", "ekf_reloc", "isam2", "isam2_reloc"):
            assert 0.0 < ok["runs"][key]["ate_rmse_m"] < 0.3
            assert ok["runs"][key]["inside_3sigma"] >= 0.9
        assert ok["fixes"]["attempts"] > 0
    lines = (out / "results.jsonl").read_text().splitlines()
    assert len(lines) == 4 and max(len(line) for line in lines) < 10_000  # no arrays over the wire
    summary = json.loads((out / "campaign.json").read_text())
    assert summary["overrides"] == SHORT


@pytest.mark.slow
def test_two_workers_give_identical_results(one_worker, cluster, tmp_path):
    _, run1 = one_worker
    run2 = run_campaign(SPEC, tmp_path, scheduler=cluster)
    assert run2.n_workers == 2
    a, b = _by_key(run1.records), _by_key(run2.records)
    assert set(a) == set(b)
    for key in a:
        assert a[key]["status"] == b[key]["status"]
        assert a[key].get("result") == b[key].get("result")
        assert a[key].get("error") == b[key].get("error")
    pids = {r["runtime"]["pid"] for r in run2.records}
    assert len(pids) == 2  # the layout really differed: tasks ran on both workers


@pytest.mark.slow
def test_resume_skips_done_tasks_and_recovers_from_a_torn_line(one_worker, cluster, tmp_path):
    _, run1 = one_worker
    first = _by_key(run1.records)
    done = json.dumps(first["my2022/base/seed0"], sort_keys=True)
    torn = json.dumps(first["my2022/base/seed1"], sort_keys=True)[:200]  # interrupted while writing
    (tmp_path / "results.jsonl").write_text(done + "\n" + torn)
    run = run_campaign(SPEC, tmp_path, scheduler=cluster)
    assert (run.computed, run.skipped) == (3, 1)  # seed 1 again, and the two failures
    recs = _by_key(run.records)
    assert recs["my2022/base/seed1"]["result"] == first["my2022/base/seed1"]["result"]
    assert (tmp_path / "results.jsonl").read_text().startswith(done + "\n")
    # a second resume: both simulated tasks are done, only the failed ones are tried again
    run = run_campaign(SPEC, tmp_path, scheduler=cluster)
    assert (run.computed, run.skipped) == (2, 2)
    # a changed override is a different computation: nothing is skipped for it
    changed = CampaignSpec(worlds=("my2022",), seeds=(0,), overrides={**SHORT, "compare.relocalizer.period_s": 4.0})
    assert [t["config_hash"] for t in expand(changed)] != [first["my2022/base/seed0"]["config_hash"]]


@pytest.mark.slow
def test_cli_campaign_on_a_scheduler(cluster, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "fgslam", "campaign", "--worlds", BAD_WORLD, "--seeds", "0-1",
                        "--out", str(out), "--scheduler", cluster, "--set", "traverse.distance_m=5"],
                       check=False, capture_output=True, text=True)
    assert r.returncode == 1, r.stderr[-2000:]  # the campaign ran; its tasks failed
    assert "2 tasks: 0 ok, 2 failed." in r.stdout
    assert (out / "summary.md").read_text() == r.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_failed"] == 2 and summary["campaign"]["overrides"] == SHORT
    assert len(read_records(out / "results.jsonl")) == 2
    r = subprocess.run([sys.executable, "-m", "fgslam", "campaign", "--worlds", "cnes", "--seeds", "0",
                        "--out", str(out), "--set", "relocaliser.period_s=3"], check=False, capture_output=True, text=True)
    assert r.returncode == 2 and "relocaliser" in r.stderr


def test_describe_of_nothing_is_empty():
    from fgslam.campaign import describe

    assert describe([None, float("nan")]) == {"mean": None, "median": None, "p90": None, "n": 0}
    assert describe([2.0]) == {"mean": 2.0, "median": 2.0, "p90": 2.0, "n": 1}
    assert np.isclose(describe([1.0, 3.0])["p90"], 2.8)


@pytest.mark.slow
def test_a_task_failing_outside_the_task_function_is_recorded(cluster, tmp_path):
    """Errors raised on the worker outside run_task's own guard (here: by the task function itself)."""

    def flaky(task):  # defined here: shipped to the workers by value
        if task["seed"] == 1:
            raise RuntimeError("worker lost its disk")
        return {**task, "status": "ok", "result": {"runs": {"isam2_reloc": {"ate_rmse_m": 0.1}}}, "runtime": {}}

    spec = CampaignSpec(worlds=("cnes",), seeds=(0, 1, 2))
    run = run_campaign(spec, tmp_path, scheduler=cluster, task_function=flaky)
    recs = _by_key(run.records)
    assert [recs[f"cnes/base/seed{s}"]["status"] for s in (0, 1, 2)] == ["ok", "error", "ok"]
    assert recs["cnes/base/seed1"]["error"] == "RuntimeError: worker lost its disk"
    assert len(read_records(tmp_path / "results.jsonl")) == 3

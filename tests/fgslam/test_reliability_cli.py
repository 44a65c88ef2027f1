"""The hostile-user cases of issue 17 through the CLI, on small synthetic traverses written as
bags: each is a clear error before any work, or a correct answer."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _synth_stream import make_stream

from fgslam.cli import main
from fgslam.io.catalog_csv import write_catalog_csv
from fgslam.io.outdir import OutputDir, read_manifest
from reloc.measurements import CmdVel, GroundTruthPose, WheelOdometry, sort_key
from sim.bag_writer import write_bag


def _input_dir(path: Path, measurements: list, catalog) -> Path:
    """A hand-made input directory (bag/ + catalog.csv), as `fgslam run DIR` and `compare` read."""
    path.mkdir(parents=True)
    write_bag(path / "bag", measurements)
    write_catalog_csv(path / "catalog.csv", catalog)
    return path


def _nan_cmd(m: CmdVel) -> CmdVel:
    """A /cmd_vel message holding NaN (CmdVel refuses to be built with one; a bag can hold it)."""
    bad = object.__new__(CmdVel)
    for f in dataclasses.fields(CmdVel):
        object.__setattr__(bad, f.name, getattr(m, f.name))
    object.__setattr__(bad, "v_mps", math.nan)
    return bad


def _ate(out: Path) -> float:
    return json.loads((out / "metrics.json").read_text())["ate"]["rmse"]


@pytest.fixture(scope="module")
def stream():
    s = make_stream(seed=7, duration_s=40.0)
    # wheel odometry measures the true speed (the commands are 5 % off: slip)
    wheel = [WheelOdometry(m.t, 0.95 * m.v_mps, m.yaw_rate_radps) for m in s.measurements if isinstance(m, CmdVel)]
    return dataclasses.replace(s, measurements=sorted(s.measurements + wheel, key=sort_key))


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory, stream) -> Path:
    return _input_dir(tmp_path_factory.mktemp("synth") / "synth", stream.measurements, stream.catalog)


def test_a_bag_without_usable_cmd_vel_drives_on_its_wheel_odometry(tmp_path, stream, synth_dir, caplog):
    """Case 1: no /cmd_vel, or every /cmd_vel NaN, with /wheel_odom: not a rover standing still."""
    (tmp_path / "wheel.yaml").write_text("runner: {speed_source: wheel}\n")
    assert main(["run", str(synth_dir), "--backend", "dr", "--no-reloc", "--out", str(tmp_path / "ref"),
                 "--config", str(tmp_path / "wheel.yaml")]) == 0
    ref = _ate(tmp_path / "ref")
    truth = [m for m in stream.measurements if isinstance(m, GroundTruthPose)]
    driven = sum(np.linalg.norm(b.position_m - a.position_m) for a, b in itertools.pairwise(truth))
    assert ref < 0.1 * driven  # standing still would be off by up to the whole traverse
    variants = {"nocmd": [m for m in stream.measurements if not isinstance(m, CmdVel)],
                "nancmd": [_nan_cmd(m) if isinstance(m, CmdVel) else m for m in stream.measurements]}
    for name, meas in variants.items():
        caplog.clear()
        d = _input_dir(tmp_path / name, meas, stream.catalog)
        assert main(["run", str(d), "--backend", "dr", "--no-reloc", "--out", str(tmp_path / f"out_{name}")]) == 0
        assert "no usable /cmd_vel message: speeds come from /wheel_odom" in caplog.text
        assert _ate(tmp_path / f"out_{name}") == pytest.approx(ref, rel=1e-9)
        import yaml

        used = yaml.safe_load((tmp_path / f"out_{name}" / "config.yaml").read_text())
        assert used["runner"]["speed_source"] == "wheel"  # the config actually used is the one saved


def test_start_pose_carries_z_and_the_imu_attitude(tmp_path, stream, caplog):
    """Case 2: --start X,Y,Z,YAW on a yard 4.47 m above the map origin; the gravity-referenced
    roll and pitch come from the IMU; --start-sigma sets the start covariance."""
    from scipy.spatial.transform import Rotation

    from fgslam.cli.cmd_run import parse_start
    from fgslam.inputs import load_bag

    high = [dataclasses.replace(m, position_m=m.position_m + [0.0, 0.0, 4.47]) if isinstance(m, GroundTruthPose) else m
            for m in stream.measurements]
    d = _input_dir(tmp_path / "high", high, stream.catalog)
    g0 = next(m for m in high if isinstance(m, GroundTruthPose))
    x, y, z = (float(v) for v in g0.position_m)
    yaw = float(Rotation.from_quat(g0.quat_xyzw).as_euler("ZYX")[0])
    args = ["run", str(d), "--backend", "dr", "--no-reloc"]
    assert main([*args, "--out", str(tmp_path / "truth")]) == 0
    assert main([*args, "--out", str(tmp_path / "xyzyaw"), "--start", f"{x!r},{y!r},{z!r},{yaw!r}"]) == 0
    assert _ate(tmp_path / "xyzyaw") == pytest.approx(_ate(tmp_path / "truth"), abs=1e-6)
    assert _ate(tmp_path / "truth") < 1.0
    caplog.clear()
    assert main([*args, "--out", str(tmp_path / "xyyaw"), "--start", f"{x!r},{y!r},{yaw!r}"]) == 0
    assert "give --start X,Y,Z,YAW" in caplog.text and _ate(tmp_path / "xyyaw") > 4.0
    # roll and pitch from the first IMU sample, yaw as given; the covariance from --start-sigma
    tilt = Rotation.from_euler("ZYX", [1.0, -0.2, 0.1])  # the IMU's yaw (1.0) is arbitrary
    tilted = [dataclasses.replace(m, quat_xyzw=(tilt * Rotation.from_quat(m.quat_xyzw)).as_quat())
              if type(m).__name__ == "ImuSample" else m for m in stream.measurements]
    td = _input_dir(tmp_path / "tilted", tilted, stream.catalog)
    inputs = load_bag(td / "bag", td / "catalog.csv", parse_start("1,2,3,0.3", "0.5,0.2,0.05"))
    ypr = Rotation.from_matrix(inputs.initial.T_world_base[:3, :3]).as_euler("ZYX")
    np.testing.assert_allclose(ypr, [0.3, -0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(inputs.initial.position_m, [1, 2, 3])
    np.testing.assert_allclose(np.diag(inputs.initial.cov)[[0, 1, 2, 5]], [0.25, 0.25, 0.04, 0.0025])


@pytest.mark.parametrize(("args", "message"), [
    (["--start", "nan,0,0"], "--start must hold finite numbers"),
    (["--start", "1,2"], "--start must be X,Y,YAW or X,Y,Z,YAW"),
    (["--start-sigma", "0.1,-1"], "--start-sigma must hold 1-sigma values > 0"),
])
def test_bad_start_options_are_named(tmp_path, synth_dir, capsys, args, message):
    """Case 8: --start nan and friends, before anything is read or written."""
    assert main(["run", str(synth_dir), "--out", str(tmp_path / "o"), *args]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("content", [None, "not a tiff"])
def test_a_bad_terrain_model_is_named_before_anything_is_written(tmp_path, synth_dir, capsys, content):
    dem = tmp_path / "dtm.tif"
    if content is not None:
        dem.write_text(content)
    assert main(["run", str(synth_dir), "--dem", str(dem), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"--dem: {dem}" in err and not (tmp_path / "o").exists()


def test_the_imu_gap_limit_is_named_and_a_bridged_gap_is_not_driven_through(tmp_path, stream, capsys, caplog):
    """Case 8: a one-hour pause of the whole recording: refused naming runner.max_imu_gap_s; with
    the limit raised, the rover is not driven for the hour at its last command."""
    paused = [dataclasses.replace(m, t=m.t + 3600.0) if m.t > 20.0 else m for m in stream.measurements]
    d = _input_dir(tmp_path / "paused", paused, stream.catalog)
    args = ["run", str(d), "--backend", "dr", "--no-reloc"]
    assert main([*args, "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "gap of 3600.0" in err and "runner.max_imu_gap_s = 1 s" in err and not (tmp_path / "o1").exists()
    (tmp_path / "gap.yaml").write_text("runner: {max_imu_gap_s: 4000}\n")
    assert main([*args, "--out", str(tmp_path / "o2"), "--config", str(tmp_path / "gap.yaml")]) == 0
    assert "/cmd_vel is silent for 3599.0 s" in caplog.text and "taken as stopped" in caplog.text
    ref_dir = _input_dir(tmp_path / "ref", stream.measurements, stream.catalog)
    assert main(["run", str(ref_dir), "--backend", "dr", "--no-reloc", "--out", str(tmp_path / "o4")]) == 0
    # the pause costs at most the 1 s the last command stays valid (0.25 m/s), not 3600 s of it
    assert _ate(tmp_path / "o2") < _ate(tmp_path / "o4") + 0.3


def test_out_is_checked_before_any_work(tmp_path, synth_dir, capsys, monkeypatch):
    """Case 7: --out a file, under a file, or not creatable: a named error first (here before the
    missing input, or the simulation, is even looked at)."""
    f = tmp_path / "file"
    f.write_text("x")
    for out, message in ((f, "exists and is not a directory"), (f / "sub", "is not a directory")):
        assert main(["run", str(tmp_path / "no_such_input"), "--out", str(out)]) == 2
        assert f"--out {out}" in (err := capsys.readouterr().err) and message in err

    def no_sim(cfg):
        raise AssertionError("simulated before --out was checked")

    monkeypatch.setattr(importlib.import_module("sim.simulate"), "simulate", no_sim)
    assert main(["sim", "--world", "my2022", "--out", str(f)]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    real_mkdir = Path.mkdir

    def read_only(self, *a, **k):  # a read-only parent, as root would not see it with chmod
        if self.name == "ro_out":
            raise PermissionError(13, "Permission denied", str(self))
        return real_mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", read_only)
    assert main(["sim", "--world", "my2022", "--out", str(tmp_path / "ro_out")]) == 2
    assert "cannot write there: Permission denied" in capsys.readouterr().err


def test_sim_does_not_replace_an_existing_bag_by_default(tmp_path, synth_dir, capsys, monkeypatch):
    """Case 4: `fgslam sim --out DIR` over a recorded bag: refused, the bag untouched."""
    def no_sim(cfg):
        raise AssertionError("simulated over a recorded bag")

    monkeypatch.setattr(importlib.import_module("sim.simulate"), "simulate", no_sim)
    before = {p: p.read_bytes() for p in synth_dir.rglob("*") if p.is_file()}
    assert main(["sim", "--world", "my2022", "--out", str(synth_dir)]) == 2  # fgslam did not write it
    assert "no fgslam manifest (bag, catalog.csv)" in capsys.readouterr().err
    assert main(["sim", "--world", "my2022", "--out", str(synth_dir), "--force"]) == 2  # and it holds a bag
    assert "already holds bag, catalog.csv; pass --overwrite to replace them" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in synth_dir.rglob("*") if p.is_file()} == before


def test_reruns_replace_the_whole_result_and_concurrent_runs_are_refused(tmp_path, synth_dir, capsys):
    """Case 6: a re-run without --rrd leaves no old recording; a second fgslam on the same --out
    stops at once instead of mixing its files with the first one's."""
    out = tmp_path / "run"
    args = ["run", str(synth_dir), "--backend", "dr", "--no-reloc", "--out", str(out)]
    assert main([*args, "--rrd", str(out / "run.rrd")]) == 0
    assert "run.rrd" in read_manifest(out)["files"]
    assert main(args) == 0
    m = read_manifest(out)
    assert not (out / "run.rrd").exists() and m["status"] == "complete" and "run.rrd" not in m["files"]
    with OutputDir(out, "run"):  # another process holding the directory
        assert main(args) == 2
        assert "another fgslam process is writing this directory" in capsys.readouterr().err
    assert read_manifest(out)["files"] == m["files"]


def _children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (Linux /proc)."""
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            kids.append(int(stat.parent.name))
    return kids + [g for k in kids for g in _children(k)]


def _alive(pids: list[int]) -> list[int]:
    out = []
    for p in pids:
        try:
            if Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.append(p)
        except OSError:
            pass
    return out


def _start_and_signal(args: list[str], sig: int, n_children: int, timeout_s: float = 120.0, settle_s: float = 0.3):
    """Start ``fgslam ARGS``, wait for ``n_children`` descendants, send ``sig`` to the parent only;
    returns (exit code, stderr, the descendants seen)."""
    # Ctrl-C raises KeyboardInterrupt even where the test runner's process ignores SIGINT
    boot = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from fgslam.cli import main; sys.exit(main())")
    proc = subprocess.Popen([sys.executable, "-c", boot, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    t0 = time.monotonic()
    kids: list[int] = []
    while time.monotonic() - t0 < timeout_s and proc.poll() is None:
        kids = _children(proc.pid)
        if len(kids) >= n_children:
            break
        time.sleep(0.05 if settle_s else 0.002)
    assert proc.poll() is None and len(kids) >= n_children, "the workers never started"
    time.sleep(settle_s)
    kids = _children(proc.pid)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    deadline = time.monotonic() + 10.0
    while _alive(kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return proc.returncode, err, kids


@pytest.fixture(scope="module")
def long_dir(tmp_path_factory) -> Path:
    s = make_stream(seed=3, duration_s=100.0)  # long enough to be interrupted while its passes run
    return _input_dir(tmp_path_factory.mktemp("long") / "long", s.measurements, s.catalog)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_compare_workers_die_with_it_and_the_previous_result_stays(tmp_path, long_dir, sig, code):
    """Cases 5 and 6: Ctrl-C, SIGTERM or SIGKILL of `fgslam compare`: no worker left behind, and
    the finished result already in --out is neither mixed nor lost."""
    out = tmp_path / "cmp"
    with OutputDir(out, "compare") as od:  # a finished earlier comparison
        for name in ("table.md", "results.json", "config.yaml", "compare.rrd"):
            (od.staging / name).write_text(f"earlier {name}")
        od.commit()
    before = {p.name: p.read_text() for p in out.iterdir()}
    rc, err, kids = _start_and_signal(["compare", str(long_dir), "--out", str(out)], sig, n_children=3)
    assert rc == code, err[-2000:]
    assert not _alive(kids), f"workers {kids} outlived their parent"
    assert {p.name: p.read_text() for p in out.iterdir() if not p.name.startswith(".staging-")} == before
    assert bool(list(out.glob(".staging-*"))) == (sig == signal.SIGKILL)  # a killed run cannot clean up
    assert read_manifest(out)["status"] == "complete"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_the_workers_are_forked_still_ends_the_comparison(tmp_path, long_dir, sig):
    """Signalled as soon as the first worker exists (the pool still forking the others): the
    comparison stops with the signal's code, no worker is left, and nothing is written (a signal
    inside the fork's bookkeeping once left a worker waited for for ever, or was dropped)."""
    out = tmp_path / "cmp"
    rc, err, kids = _start_and_signal(["compare", str(long_dir), "--out", str(out)], sig, n_children=1, settle_s=0.0)
    assert rc == 128 + sig, err[-2000:]
    assert "Exception ignored" not in err, err[-2000:]
    assert not _alive(kids), f"workers {kids} outlived their parent"
    assert not out.exists() or not list(out.glob("results.json"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks")
def test_kill_pool_leaves_no_worker_and_no_pool_thread_for_the_exit_hook():
    """A killed pool's manager thread has ended and closed its wake-up pipe before kill_pool
    returns: the interpreter's exit hook then finds nothing to write to (a close racing its write
    once printed "Exception ignored ... Bad file descriptor" after a SIGTERM)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from fgslam.lifetime import kill_pool, worker_initializer

    pool = ProcessPoolExecutor(max_workers=2, mp_context=mp.get_context("fork"),
                               initializer=worker_initializer, initargs=(os.getpid(),))
    futures = [pool.submit(time.sleep, 30.0) for _ in range(3)]
    deadline = time.monotonic() + 10.0
    while len(mp.active_children()) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    manager, wakeup = pool._executor_manager_thread, pool._executor_manager_thread_wakeup
    workers = list(pool._processes.values())
    kill_pool(pool)
    assert not any(p.is_alive() for p in workers)
    assert not manager.is_alive()
    assert wakeup._closed
    assert all(f.done() for f in futures)


def test_signals_deferred_holds_a_signal_to_the_end_of_the_block():
    from fgslam.lifetime import Terminated, signals_deferred, terminate_on_sigterm

    done = []
    with terminate_on_sigterm(), pytest.raises(Terminated):
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler has had every chance to run
            done.append("block finished")
    assert done == ["block finished"]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL or callable(signal.getsignal(signal.SIGTERM))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_campaign_workers_die_with_a_killed_campaign(tmp_path):
    """Case 5 for the Dask workers of a campaign: SIGKILL of `fgslam campaign` leaves none."""
    pytest.importorskip("distributed")
    rc, _, kids = _start_and_signal(["campaign", "--worlds", "my2022", "--seeds", "0-1", "--set",
                                       "traverse.distance_m=3", "--workers", "1", "--out", str(tmp_path / "camp")],
                                      signal.SIGKILL, n_children=2)
    assert rc == -9 and not _alive(kids), f"Dask processes {_alive(kids)} outlived the campaign"
    assert read_manifest(tmp_path / "camp")["status"] == "incomplete"


def test_catalog_errors_name_the_option_and_write_no_unusable_file(tmp_path, capsys):
    """Case 8: --origin nan is named; an image with no rocks gives no catalog that `run` would reject."""
    import cv2

    img = tmp_path / "blank.png"
    cv2.imwrite(str(img), np.full((320, 320, 3), 128, np.uint8))
    assert main(["catalog", str(img), "--gsd", "0.05", "--origin", "nan", "0", "--out", str(tmp_path / "c.csv")]) == 2
    assert "--origin must be two finite numbers" in capsys.readouterr().err
    assert main(["catalog", str(img), "--gsd", "0.05", "--out", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err
    assert "0 rocks detected, a catalog needs at least 3" in err and not (tmp_path / "c.csv").exists()
    assert os.listdir(tmp_path) == ["blank.png"]


def test_a_signalled_process_ends_even_when_its_shutdown_would_wait_for_ever():
    """After a signal, cleanup done, the interpreter's own shutdown waits for every non-daemon
    thread: one stuck for ever (like a worker left in an odd state) no longer keeps it alive."""
    code = ("import sys, threading, time; from fgslam.lifetime import exit_watchdog; "
            "threading.Thread(target=time.sleep, args=(3600,)).start(); "
            "exit_watchdog(143, grace_s=0.5); sys.exit(143)")
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 143
    assert time.monotonic() - t0 < 30
    assert "did not finish" in proc.stderr


def test_run_and_compare_take_a_sim_directory_calibration_unless_told_otherwise(tmp_path):
    """A kilometre sim directory's backend.yaml sizes the back-ends' calibration to its sensors:
    `fgslam run DIR` and `fgslam compare DIR...` take it unless --config names another; directories
    whose backend.yaml differ (or only some with one) cannot share one comparison config: refused
    before any work, naming them."""
    from fgslam.cli.cmd_run import compare_dirs_config, sim_dir_config
    from fgslam.errors import InputFileError

    d, e, yard = tmp_path / "km", tmp_path / "km2", tmp_path / "yard"
    for x in (d, e, yard):
        x.mkdir()
    assert sim_dir_config(d, None) is None and sim_dir_config(None, None) is None
    assert compare_dirs_config([d, yard], None) is None
    (d / "backend.yaml").write_text("backend_overrides: {ekf: {rock_cov_scale: 4.0}}\n")
    other = tmp_path / "other.yaml"
    assert sim_dir_config(d, None) == d / "backend.yaml" and sim_dir_config(d, other) == other
    assert compare_dirs_config([d], None) == d / "backend.yaml"
    assert compare_dirs_config([d, yard], other) == other
    with pytest.raises(InputFileError, match="no backend.yaml: .*yard"):
        compare_dirs_config([d, yard], None)
    (e / "backend.yaml").write_text("backend_overrides:\n  ekf:\n    rock_cov_scale: 4.0\n")  # the same mapping
    assert compare_dirs_config([d, e], None) == d / "backend.yaml"
    (e / "backend.yaml").write_text("backend_overrides: {ekf: {rock_cov_scale: 2.0}}\n")
    with pytest.raises(InputFileError, match="backend.yaml #1: .*km; backend.yaml #2: .*km2"):
        compare_dirs_config([d, e], None)


def test_compare_refuses_directories_with_different_calibrations_before_any_work(tmp_path, capsys):
    """Through the CLI: the error names the directories, nothing is computed and OUT is not made."""
    d, yard = tmp_path / "km", tmp_path / "yard"
    d.mkdir()
    yard.mkdir()
    (d / "backend.yaml").write_text("backend_overrides: {}\n")
    out = tmp_path / "cmp"
    assert main(["compare", str(d), str(yard), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "different back-end calibrations" in err and str(yard) in err
    assert not out.exists()

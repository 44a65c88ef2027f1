"""rerun (issue 16): the recording's error curves hold the run's own values (the final curve's
median is metrics.json's ATE median; the 3-sigma bound is another series in another shade), poses
carry a heading arrow, and a run streams live, pose by pose while it runs, to a viewer
(--connect) or to a gRPC server it starts bound to 127.0.0.1 (--serve)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _synth_stream import make_stream, write_input_dir

from fgslam.cli import main
from fgslam.viz import rerun_log

RERUN = str(Path(sys.executable).parent / "rerun")


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    return write_input_dir(tmp_path_factory.mktemp("live") / "synth", make_stream(seed=2, duration_s=30.0))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _series(path: Path) -> dict[str, np.ndarray]:
    """Entity path -> the scalar values logged on it (time-varying rows only)."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for c in RrdReader(path).stream():
        if c.is_static:
            continue
        rb = c.to_record_batch()
        for i, name in enumerate(rb.schema.names):
            if name.endswith("Scalars:scalars"):
                out.setdefault(c.entity_path, []).extend(v for row in rb.column(i).to_pylist() for v in row)
    return {k: np.asarray(v, float) for k, v in out.items()}


def _entities(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {c.entity_path for c in RrdReader(path).stream()}


def test_the_recorded_errors_are_the_runs_values(synth_dir, tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(synth_dir), "--backend", "ekf", "--out", str(out), "--rrd", str(out / "run.rrd")]) == 0
    met = json.loads((out / "metrics.json").read_text())
    series = _series(out / "run.rrd")
    w = "/synth/errors/position/ekf_reloc"
    # the final trajectory's error, sampled along the path (the recording grows with distance, not
    # with the pose rate): the run's own errors at those poses, and their median close to the ATE's
    from fgslam import metrics
    from fgslam.io.tum import read_tum

    final, gt = read_tum(out / "ekf_reloc.tum"), read_tum(out / "ground_truth.tum")
    k = rerun_log.path_samples(final.t, final.positions_m)
    err, _ = metrics.position_errors(type(final)(final.t[k], final.T_world_base[k]), gt)
    np.testing.assert_allclose(series[f"{w}_final"], np.linalg.norm(err, axis=1), rtol=1e-6, atol=1e-9)
    assert np.median(series[f"{w}_final"]) == pytest.approx(met["ate"]["median"], rel=0.1)
    # the bound is its own series, larger than the error, drawn lighter and thinner
    assert np.median(series[f"{w}_3sigma"]) > np.median(series[w])
    assert rerun_log._shade((31, 119, 180), "3σ") != rerun_log._shade((31, 119, 180), "error")
    assert rerun_log.SERIES_WIDTH["3σ"] < rerun_log.SERIES_WIDTH["error"]
    assert "/synth/ekf_reloc/heading" in _entities(out / "run.rrd")


def _entities_when_written(path: Path, wanted: set[str], timeout_s: float = 60.0) -> set[str]:
    """The entities of the file a viewer saves as it receives (``rerun --save`` writes each message
    when it arrives), read until ``wanted`` are there or ``timeout_s`` passed."""
    ents: set[str] = set()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            ents = _entities(path)
        except Exception:  # not there yet, or a message half written
            ents = set()
        if wanted <= ents:
            break
        time.sleep(0.5)
    return ents


@contextlib.contextmanager
def _saving_viewer(saved: Path):
    """A rerun viewer on a free 127.0.0.1 port that saves what it receives to ``saved`` as it
    arrives; yields its gRPC URL once it listens, and stops it afterwards."""
    port = _free_port()
    viewer = subprocess.Popen([RERUN, "--bind", "127.0.0.1", "--port", str(port), "--save", str(saved)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        for _ in range(200):
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        yield rerun_log.viewer_url(port)
    finally:
        # the viewer's own shutdown is not under test (under load it has taken > 30 s). `rerun` is
        # a Python launcher whose child is the viewer binary: the signals go to the whole process
        # group (its own session), or the binary outlives the test, orphaned
        rerun_log.signal_viewer(viewer.pid, signal.SIGINT)
        try:
            viewer.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        rerun_log.signal_viewer(viewer.pid, signal.SIGKILL)
        viewer.wait()


def _running() -> list[tuple[int, int, list[str]]]:
    """(pid, process group, command line) of every running process (zombies left out), from /proc."""
    out = []
    for d in Path("/proc").glob("[0-9]*"):
        try:
            state, _, pgid = (d / "stat").read_text().rsplit(")", 1)[1].split()[:3]
            cmdline = (d / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:  # ended while listed
            continue
        if state != "Z":
            out.append((int(d.name), int(pgid), cmdline))
    return out


def _ends(alive, timeout_s: float = 10.0) -> bool:
    """Whether ``alive()`` turns false within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while alive():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


def test_a_run_streams_to_a_viewer_it_connects_to(synth_dir, tmp_path):
    saved = tmp_path / "received.rrd"
    wanted = {"/synth/ekf_reloc/path", "/synth/ekf_reloc/pose", "/synth/errors/position/ekf_reloc"}
    with _saving_viewer(saved) as url:
        assert main(["run", str(synth_dir), "--backend", "ekf", "--out", str(tmp_path / "o"), "--connect", url]) == 0
        ents = _entities_when_written(saved, wanted)
    assert wanted <= ents


def _pose_times(path: Path, entity: str) -> list[float]:
    """Stream seconds of the rows logged on ``entity`` in a saved recording ([] while unreadable)."""
    from rerun.chunk import RrdReader

    out: list[float] = []
    try:
        for c in RrdReader(path).stream():
            if c.entity_path == entity and not c.is_static:
                rb = c.to_record_batch()
                out += [v.total_seconds() for v in rb.column(rb.schema.names.index(rerun_log.TIMELINE)).to_pylist()]
    except Exception:  # not there yet, or a message half written
        return []
    return sorted(out)


def test_a_run_streams_pose_by_pose_while_it_runs(synth_dir, tmp_path):
    """Halfway through the stream the runner waits: by then the viewer has received the poses up
    to that time (and none beyond it); the finished run then adds its path and final error."""
    from fgslam.backends.registry import make_backend
    from fgslam.inputs import load_sim_dir, truth_of
    from fgslam.runner import run_backend

    saved = tmp_path / "received.rrd"
    pose = "/synth/ekf/pose"
    with _saving_viewer(saved) as url:
        inputs = load_sim_dir(synth_dir)
        gt = truth_of(inputs)
        live = rerun_log.LiveRun(url, "synth", "ekf", inputs, gt)
        t_mid = 0.5 * (gt.t[0] + gt.t[-1])
        seen: dict[str, list[float]] = {}

        def stream():
            for m in inputs.measurements:
                if m.t >= t_mid and "mid" not in seen:  # the run pauses here until the viewer has its poses
                    deadline = time.monotonic() + 60.0
                    while time.monotonic() < deadline:
                        seen["mid"] = _pose_times(saved, pose)
                        if seen["mid"] and seen["mid"][-1] >= t_mid - 2 * rerun_log.LIVE_STEP_S:
                            break
                        time.sleep(0.3)
                yield m

        res = run_backend(make_backend("ekf", inputs.initial), stream(), observer=live)
        live.finish(res)
        ents = _entities_when_written(saved, {"/synth/ekf/path", "/synth/errors/position/ekf_final"})
    mid = seen["mid"]
    assert mid and t_mid - 2 * rerun_log.LIVE_STEP_S <= mid[-1] < t_mid  # up to the pause, nothing later
    assert len(mid) >= 0.4 * (t_mid - gt.t[0]) / rerun_log.LIVE_STEP_S  # about one a second (or per 1 m)
    assert live.n_poses > len(mid) and {"/synth/ekf/path", "/synth/errors/position/ekf_final"} <= ents


def test_serve_starts_a_server_on_localhost_only(synth_dir, tmp_path, capsys):
    port = _free_port()
    assert main(["run", str(synth_dir), "--backend", "dr", "--no-reloc", "--out", str(tmp_path / "o"),
                 "--serve", str(port)]) == 0
    err = capsys.readouterr().err
    pid = int(err.split("(pid ")[1].split(")")[0])
    try:
        listening = set()
        for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            if state == "0A":  # LISTEN
                ip, p = local.split(":")
                listening.add((ip, int(p, 16)))
        assert ("0100007F", port) in listening and ("00000000", port) not in listening
        assert f"rerun --connect {rerun_log.viewer_url(port)}" in " ".join(err.split())
        assert f"kill -- -{pid}" in " ".join(err.split())
    finally:
        os.killpg(pid, signal.SIGTERM)  # as the message says: the launcher and the server binary
    # the whole group ends (a plain kill of the launcher orphaned the server)
    assert _ends(lambda: any(g == pid for _, g, _ in _running()))
    assert main(["run", str(synth_dir), "--out", str(tmp_path / "x"), "--spawn", "--serve", "1"]) == 2


def test_a_viewer_that_does_not_listen_in_time_is_stopped_whole():
    from fgslam.errors import FgslamError

    port = str(_free_port())
    with pytest.raises(FgslamError, match="did not listen"):
        rerun_log.start_viewer(int(port), serve_only=True, timeout_s=1e-6)
    # the launcher and the binary it started (found by their port argument) both end
    assert _ends(lambda: any(port in cmd for _, _, cmd in _running()))

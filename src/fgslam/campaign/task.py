"""One campaign task, a pure function importable on any Dask worker: simulate one (world, seed)
with the task's overrides, compare EKF and iSAM2 with and without relocalization, and return a
small JSON-ready record (never arrays).

The record splits what the inputs determine (``result``: accuracy, fixes, consistency; identical
on any cluster layout) from what the machine determines (``runtime``: wall times, real-time
factor, worker host). A failure is caught and returned as ``status: "error"`` with its text.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import tempfile
import threading
import time
import traceback
from pathlib import Path

log = logging.getLogger(__name__)

# A worker with several threads runs one comparison at a time: a comparison already uses the
# worker's cores (its passes run on forked processes), and overlapping ones would only thrash.
_COMPARE_LOCK = threading.Lock()

_ATE_FIELDS = ("rmse", "mean", "median", "p90", "max")


def _num(v) -> float | None:
    """Finite float or None (strict JSON has no NaN)."""
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def summarise_run(run: dict, baseline: str) -> dict:
    """Small view of one variant's metrics (see :func:`fgslam.compare.run_metrics`); metres, radians, %."""
    out: dict = {f"ate_{k}_m": _num(run.get("ate", {}).get(k)) for k in _ATE_FIELDS}
    out["ate_se2_rmse_m"] = _num(run.get("ate_se2_aligned", {}).get("rmse"))
    out["rpe_rmse_m"] = _num(run.get("rpe", {}).get("rmse"))
    out["drift_pct"] = _num(run.get("drift_pct"))  # final planar error per distance travelled
    out["improvement_over_own_pct"] = _num(run.get("ate_improvement_over_own_pct"))
    out["improvement_over_baseline_pct"] = _num(run.get(f"ate_improvement_over_{baseline}_pct"))
    cons = run.get("consistency", {})
    out["inside_3sigma"] = _num(cons.get("inside_3sigma"))
    out["nees_mean"] = _num(cons.get("nees_mean"))
    for part in ("position", "yaw", "height"):  # what pooling across seeds needs (fgslam.nees.pooled_test)
        test = cons.get(part) or {}
        out[f"nees_{part}"] = {"mean": _num(test.get("mean")), "n": int(test.get("n", 0)),
                               "n_eff": _num(test.get("n_eff")), "dof": int(test.get("dof", 0))}
    out["fixes_accepted"] = int(run.get("fixes", {}).get("accepted", 0))
    out["n_landmarks"] = int(run.get("n_landmarks", 0))
    return out


def summarise_fixes(fx: dict) -> dict:
    """The shared fix list's statistics (reference pass): counts, rate in Hz, errors in m / rad."""
    pos, yaw, within = fx.get("position_error_m", {}), fx.get("yaw_error_rad", {}), fx.get("within_m", {})
    return {
        "attempts": int(fx.get("attempts", 0)),
        "fixes": int(fx.get("fixes", 0)),
        "rate_hz": _num(fx.get("rate_hz")),
        "position_error_median_m": _num(pos.get("median")),
        "position_error_p90_m": _num(pos.get("p90")),
        "yaw_error_median_rad": _num(yaw.get("median")),
        "within_0.5m": _num(within.get("0.5")),
        "within_1m": _num(within.get("1")),
        "within_2m": _num(within.get("2")),
        "nees_mean": _num(fx.get("nees_mean")),
    }


def summarise_comparison(metrics: dict, baseline: str) -> tuple[dict, dict]:
    """(result, runtime) from ``WorldComparison.metrics``; ``baseline`` is the first back-end (EKF)."""
    runs = metrics["runs"]
    ref = f"{metrics['reference_backend']}_reloc"
    result = {
        "distance_m": _num(metrics.get("distance_m")),
        "duration_s": _num(metrics.get("duration_s")),
        "baseline": baseline,
        "reference": ref,
        "runs": {k: summarise_run(r, baseline) for k, r in runs.items()},
        "fixes": summarise_fixes(runs[ref]["fixes"]) if ref in runs else {},
    }
    runtime = {
        "compare_s": _num(metrics.get("wall_s")),
        "real_time_factor": _num(metrics.get("real_time_factor")),
        "runs_wall_s": {k: _num(r.get("runtime", {}).get("wall_s")) for k, r in runs.items()},
        "runs_update_p99_ms": {k: _num(r["runtime"]["update_p99_ms"]) for k, r in runs.items()
                               if r.get("runtime", {}).get("update_p99_ms") is not None},
        "runs_frame_cpu_p99_ms": {k: _num(r["runtime"]["frame_cpu_p99_ms"]) for k, r in runs.items()
                                  if r.get("runtime", {}).get("frame_cpu_p99_ms") is not None},
        # the worker process's high-water mark when each pass ended (its passes run one after
        # another, and a worker keeps its mark across the tasks it ran before)
        "runs_peak_rss_mb": {k: _num(max(m["peak_rss_mb"] for m in r["memory"])) for k, r in runs.items()
                             if r.get("memory")},
    }
    runtime["peak_rss_mb"] = max((v for v in runtime["runs_peak_rss_mb"].values() if v is not None), default=None)
    return result, runtime


def _yard_inputs(task: dict):
    """A yard or Gazebo world simulated in memory, and the comparison config of the task."""
    import dataclasses

    from fgslam.campaign.spec import build_configs
    from fgslam.inputs import RunInputs
    from sim.simulate import simulate

    sim_cfg, cmp_cfg = build_configs(task.get("overrides", {}))
    sim_cfg = dataclasses.replace(sim_cfg, world=task["world"], seed=int(task["seed"]))
    run = simulate(sim_cfg)
    inputs = RunInputs(
        name=os.path.basename(str(task["world"]).rstrip("/")) or str(task["world"]),
        measurements=list(run.measurements), catalogs={"rocks": run.catalog}, initial=run.initial_pose,
        source={"kind": "simulator", "world": str(task["world"]), "seed": int(task["seed"])},
    )
    return inputs, cmp_cfg


def _kilometre_inputs(task: dict, workdir: Path):
    """A kilometre preset streamed to a bag in ``workdir`` (the worker's own disk: a whole traverse
    is 0.2-1 GB) and read back lazily with every catalog it wrote (rocks, craters), as ``fgslam
    run`` takes a ``fgslam sim`` directory; the comparison config is the run's ``backend.yaml`` (the
    back-ends' calibration for its sensors) under the task's comparison overrides."""
    from fgslam.campaign.spec import build_configs
    from fgslam.config_file import compare_overrides, read_yaml_mapping
    from fgslam.inputs import load_sim_dir
    from sim.tiled.outputs import simulate_to_bag

    world, seed, overrides = task["world"], int(task["seed"]), task.get("overrides", {})
    sim_cfg, _ = build_configs(overrides, world, seed)
    sim_dir = workdir / "sim"
    simulate_to_bag(sim_cfg, sim_dir, overwrite=False)
    inputs = load_sim_dir(sim_dir)
    inputs.name = world
    inputs.source = {"kind": "simulator", "world": world, "seed": seed}
    base = compare_overrides(read_yaml_mapping(sim_dir / "backend.yaml"))
    _, cmp_cfg = build_configs(overrides, world, seed, compare_base=base)
    return inputs, cmp_cfg


TASK_DIR_PREFIX = "fgslam-task-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        pass
    return True


def sweep_task_dirs(root: str | os.PathLike | None = None) -> list[Path]:
    """Remove the task directories (``fgslam-task-<pid>-*`` in ``root``, the temporary directory by
    default) whose process is gone: a worker killed in a task (the nanny's SIGKILL, a lost
    machine) cannot remove its bag, up to ~0.6 GB for a whole kilometre traverse, so the next
    task on the machine does. Returns the directories removed."""
    import shutil

    root = Path(root if root is not None else tempfile.gettempdir())
    removed = []
    for d in root.glob(f"{TASK_DIR_PREFIX}*-*"):
        pid = d.name[len(TASK_DIR_PREFIX):].split("-", 1)[0]
        if d.is_dir() and pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
            log.info("removed %s, left by a task whose process is gone", d)
    return removed


def run_task(task: dict) -> dict:
    """Simulate ``task`` (world, seed, overrides; see :func:`fgslam.campaign.spec.expand`), run the
    comparison in this process and return the task's record (status "ok" or "error"). A kilometre
    preset is streamed through a temporary directory removed with the task (or, if the process is
    killed, by the next task on the machine: :func:`sweep_task_dirs`)."""
    t0 = time.perf_counter()
    record = {k: task[k] for k in ("key", "world", "variant", "seed", "config_hash")}
    record["overrides"] = task.get("overrides", {})
    runtime: dict = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        from fgslam.compare import compare_world
        from sim.tiled.presets import is_tiled

        sweep_task_dirs()
        with tempfile.TemporaryDirectory(prefix=f"{TASK_DIR_PREFIX}{os.getpid()}-") as tmp:
            if is_tiled(task["world"]):
                inputs, cmp_cfg = _kilometre_inputs(task, Path(tmp))
            else:
                inputs, cmp_cfg = _yard_inputs(task)
            t_sim = time.perf_counter()
            with _COMPARE_LOCK:
                wc = compare_world(inputs, cmp_cfg)
        result, rt = summarise_comparison(wc.metrics, cmp_cfg.backends[0])
        runtime.update(sim_s=t_sim - t0, **rt)
        record.update(status="ok", result=result)
    except Exception as exc:  # noqa: BLE001 -- a task's failure is data for the campaign, not its end
        log.warning("task %s failed: %s", task.get("key"), exc)
        record.update(status="error", error=f"{type(exc).__name__}: {exc}",
                      traceback=traceback.format_exc(limit=12))
    runtime["task_s"] = time.perf_counter() - t0
    record["runtime"] = runtime
    return record

"""``fgslam bench faults``: every fault scenario of ``SimConfig.faults`` through both back-ends.

One short seeded yard traverse, simulated once per scenario (the fault-free run, then each fault
alone on the same world, route and seed), written as a ``fgslam sim`` directory and read back
from its bag (so the recorder's jitter meets the real reader), then compared as ``fgslam
compare`` does: EKF and iSAM2, each without and with relocalization (the fixes of the reference
pass, replayed to the other). The wrong-fix scenario wraps the reference pass's relocalizer
(:mod:`fgslam.fault_fixes`). Every pass starts from one draw of the start's claimed prior
(``draw_start``, the comparison's, seeded with the simulator's seed), as a Monte Carlo
consistency test must.

Per scenario and variant (:func:`fault_metrics`, on the online estimate, the one a rover acts on):

- ``blind``: the two-sided NEES test (:mod:`fgslam.nees`, planar position, 2 dof, effective
  sample size) over the fault window: inside its 95 % interval is the goal;
- ``sigma_growth``: planar position sigma at the window's end over the one at its start;
- ``end_ratio``: RMSE of the planar error over the last ``end_window_s`` of the run, over the
  fault-free run's ATE (RMSE of the same variant): at most 2 is the goal;
- ``recovery_s``: time from the window's end until the planar error stays below 2x that
  fault-free ATE to the end of the run (None: it never does).

Over several seeds (:func:`pooled`), per scenario and variant: the blind windows' NEES pooled as
a campaign's ANEES (one window is often a single draw of the drift, so its own interval is wide;
the seeds' effective sizes add up), and how many seeds meet each goal.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam import metrics as M
from fgslam.compare import CompareConfig, run_key, run_label
from fgslam.nees import NeesTest, pooled_test, whitened_test
from reloc.config import NonNegative, Positive, checked
from reloc.errors import ConfigError

log = logging.getLogger(__name__)

Tick = Callable[[str, int], Callable[[], None]]
FAULT_FREE = "none"
END_RATIO_GOAL = 2.0


@checked(ConfigError)
@dataclass(frozen=True)
class FaultBenchConfig:
    """The world of the table and each scenario's fault window (s after the run's start)."""

    world: str = "my2020"
    seed: int = 0
    distance_m: Positive = 24.0  # my2020 at its preset speed: about 250 s; dense rocks, fixes from the start
    start_s: NonNegative = 60.0
    duration_s: Positive = 120.0  # blackout, no rocks, IMU bias step
    stuck_s: Positive = 60.0
    wrong_fix_s: Positive = 60.0
    jitter_s: Positive = 0.01
    end_window_s: Positive = 20.0
    # the start pose drawn from its claimed prior (seeded, the same for every scenario of a seed):
    # started at the exact truth, the variants without fixes kept the start's 1 cm / 0.002 rad in
    # their covariance and no error to match it (iSAM2, fault-free, 3 seeds: NEES 0.32 pessimistic)
    draw_start: bool = True


def scenarios(cfg: FaultBenchConfig) -> dict:
    """Scenario name -> :class:`sim.faults.FaultsConfig` (the fault-free one first)."""
    from sim import faults as F

    w = {"start_s": cfg.start_s, "duration_s": cfg.duration_s}
    return {
        FAULT_FREE: F.FaultsConfig(),
        "camera_blackout": F.FaultsConfig(camera_blackout=F.CameraBlackout(**w)),
        "no_rocks": F.FaultsConfig(no_rocks=F.NoRocks(**w)),
        "imu_bias_step": F.FaultsConfig(imu_bias_step=F.ImuBiasStep(**w)),
        "stuck": F.FaultsConfig(stuck=F.Stuck(start_s=cfg.start_s, duration_s=cfg.stuck_s)),
        "timestamp_jitter": F.FaultsConfig(timestamp_jitter=F.TimestampJitter(jitter_s=cfg.jitter_s)),
        "wrong_fixes": F.FaultsConfig(wrong_fixes=F.WrongFixesConfig(start_s=cfg.start_s, duration_s=cfg.wrong_fix_s)),
    }


def _planar(res, gt):
    """(t, planar error (K,), planar sigma (K,), whitened planar error (K, 2)) of a pass's online
    estimate."""
    _, series = M.consistency(res.online, gt)
    err = np.linalg.norm(series["err_xy"], axis=1)
    sigma = np.linalg.norm(series["sigma_xy"], axis=1)
    return series["t"], err, sigma, series["white_xy"]


def recovery_s(t: np.ndarray, err: np.ndarray, t_end_fault: float, level_m: float) -> float | None:
    """Seconds after ``t_end_fault`` from which ``err`` (K,) stays <= ``level_m`` to the end
    (0 when it never left it); None when the last sample is above it."""
    after = t >= t_end_fault
    if not after.any() or err[-1] > level_m:
        return None
    above = np.flatnonzero(after & (err > level_m))
    if above.size == 0:
        return 0.0
    return float(t[min(above[-1] + 1, len(t) - 1)] - t_end_fault)


def fault_metrics(res, gt, window: tuple[float, float] | None, free_ate_m: float, end_window_s: float,
                  reference: bool = False) -> dict:
    """The fault figures of one pass (see module doc); ``reference``: the fault-free run, whose
    NEES test over ``window`` (the scenarios' nominal window) is the yardstick of the others."""
    t, err, sigma, white_xy = _planar(res, gt)
    end = t >= t[-1] - end_window_s
    out = {"ate_m": M.ate(res.final, gt).rmse, "ate_online_m": float(np.sqrt(np.mean(err**2))),
           "end_rmse_m": float(np.sqrt(np.mean(err[end] ** 2))), "max_err_m": float(err.max())}
    out["end_ratio"] = out["end_rmse_m"] / free_ate_m if free_ate_m > 0 else math.nan
    out["accepted_fixes"] = sum(1 for o in res.outcomes if o.accepted)
    out["rejected_fixes"] = sum(1 for o in res.outcomes if not o.accepted)
    # what the front-end monitors saw (reloc.slip, reloc.gyro): detections outside a fault are false alarms
    out["monitors"] = {k: res.extra[k] for k in ("slip", "gyro") if k in res.extra}
    if window is None:
        return out
    a, b = window
    if reference:  # the fault-free run over the nominal window: how consistent the variant is anyway
        out["blind"] = whitened_test(white_xy[(t >= a) & (t < b)]).to_dict()
        return out
    blind = (t >= a) & (t < b)
    test = whitened_test(white_xy[blind])
    out["blind"] = test.to_dict()
    ia, ib = np.flatnonzero(blind)[[0, -1]] if blind.any() else (0, 0)
    out["sigma_growth"] = float(sigma[ib] / max(sigma[ia], 1e-12))
    out["recovery_s"] = recovery_s(t, err, b, END_RATIO_GOAL * free_ate_m)
    out["fixes_in_window"] = sum(1 for f in res.fixes_sent if a <= f.t_meas < b)
    out["accepted_in_window"] = sum(1 for o in res.outcomes if o.accepted and a <= o.fix.t_meas < b)
    return out


def goals_met(m: dict) -> dict:
    """Per goal, whether a scenario's figures meet it: finished, consistent while blind, end ratio."""
    blind = m.get("blind")
    return {"finished": "error" not in m,
            "consistent_blind": blind is not None and blind["verdict"] == "consistent",
            "end_within_2x": "end_ratio" in m and m["end_ratio"] <= END_RATIO_GOAL}


def _scenario_window(name: str, stats: dict, t_end: float, t0: float, cfg: FaultBenchConfig) -> tuple[float, float]:
    if name == FAULT_FREE:
        return t0 + cfg.start_s, min(t0 + cfg.start_s + cfg.duration_s, t_end)
    a, b = stats["faults"][name]
    return float(a), float(min(b, t_end))


def run_fault_bench(cfg: FaultBenchConfig, compare_cfg: CompareConfig | None = None, sim_overrides: dict | None = None,
                    tick: Tick | None = None, only: tuple[str, ...] | None = None) -> dict:
    """Simulate and compare every scenario (or those in ``only``, the fault-free one always);
    returns the results (plain data: per scenario, per variant the :func:`fault_metrics`)."""
    from fgslam.compare import compare_world, relocalizer_set
    from fgslam.fault_fixes import with_wrong_fixes
    from fgslam.inputs import load_sim_dir
    from fgslam.io.sim_dir import write_sim_dir
    from reloc.config import config_from_dict, config_to_dict
    from sim.config import SimConfig, TraverseConfig
    from sim.simulate import simulate

    compare_cfg = dataclasses.replace(compare_cfg or CompareConfig(), draw_start=cfg.draw_start)
    variants = variants_of(compare_cfg)
    tick = tick or (lambda name, total: (lambda: None))
    base = config_from_dict(SimConfig, sim_overrides or {})
    base = dataclasses.replace(base, world=cfg.world, seed=cfg.seed,
                               traverse=dataclasses.replace(base.traverse or TraverseConfig(), distance_m=cfg.distance_m))
    todo = {k: v for k, v in scenarios(cfg).items() if only is None or k == FAULT_FREE or k in only}
    step = tick(f"fault scenarios on {cfg.world} (seed {cfg.seed})", len(todo))
    results: dict = {}
    free_ate: dict = {}
    with tempfile.TemporaryDirectory(prefix="fgslam-faults-") as tmp:
        for name, faults in todo.items():
            w0 = time.perf_counter()
            sim_cfg = dataclasses.replace(base, faults=faults)
            run = simulate(sim_cfg)
            write_sim_dir(run, Path(tmp) / name)
            inputs = load_sim_dir(Path(tmp) / name)
            relocs = relocalizer_set(inputs, compare_cfg)
            t_end = float(run.ground_truth.t[-1])
            window = _scenario_window(name, run.stats, t_end, float(run.ground_truth.t[0]), cfg)
            if faults.wrong_fixes is not None:
                relocs = with_wrong_fixes(relocs, faults.wrong_fixes, window, cfg.seed)
            entry: dict = {"window_s": list(window), "duration_s": t_end - float(run.ground_truth.t[0]),
                           "distance_m": run.stats["distance_m"], "sim_config": config_to_dict(sim_cfg.faults),
                           "runs": {}}
            try:
                wc = compare_world(inputs, compare_cfg, relocalizers=relocs)
            except Exception as exc:  # a crash is a result of this benchmark, reported per scenario
                log.exception("scenario %s failed", name)
                entry["runs"] = {k: {"error": f"{type(exc).__name__}: {exc}"} for k in variants}
            else:
                for k in variants:
                    if name == FAULT_FREE:
                        free_ate[k] = float(np.sqrt(np.mean(_planar(wc.runs[k], wc.gt)[1] ** 2)))
                    entry["runs"][k] = fault_metrics(wc.runs[k], wc.gt, window, free_ate.get(k, math.nan),
                                                     cfg.end_window_s, reference=name == FAULT_FREE)
                entry["wall_s"] = time.perf_counter() - w0
            results[name] = entry
            step()
    return {"bench": config_to_dict(cfg), "compare_config": config_to_dict(compare_cfg), "variants": list(variants),
            "free_ate_online_m": free_ate, "scenarios": results}


def pooled(by_seed: dict) -> dict:
    """Several seeds' :func:`run_fault_bench` results (seed -> results) summed up per scenario and
    variant: ``blind`` the pooled NEES test of the seeds' blind windows (ANEES, :func:`fgslam.nees.pooled_test`),
    ``goals`` how many seeds meet each of :func:`goals_met`, ``seeds`` how many ran it, ``ate_m`` the
    seeds' ATE."""
    out: dict = {}
    for seed, res in by_seed.items():
        for name, entry in res["scenarios"].items():
            for k, m in entry["runs"].items():
                cell = out.setdefault(name, {}).setdefault(k, {"seeds": 0, "goals": {}, "ate_m": {}, "_tests": []})
                cell["seeds"] += 1
                if "error" not in m:
                    cell["ate_m"][str(seed)] = m["ate_m"]
                if m.get("blind") and m["blind"]["n"] > 0:
                    cell["_tests"].append(NeesTest.from_dict(m["blind"]))
                if name != FAULT_FREE:
                    for g, ok in goals_met(m).items():
                        cell["goals"][g] = cell["goals"].get(g, 0) + int(ok)
    for cells in out.values():
        for cell in cells.values():
            tests = cell.pop("_tests")
            cell["blind"] = pooled_test(tests).to_dict() if tests else None
    return out


def markdown_pooled(by_seed: dict, pool: dict) -> str:
    """The seeds' summary table: per scenario and variant, the pooled NEES while blind and the
    seeds meeting the end goal."""
    first = next(iter(by_seed.values()))
    b = first["bench"]
    variants = tuple(first.get("variants", VARIANTS))
    seeds = ", ".join(str(s) for s in by_seed)
    lines = [f"### Fault scenarios over seeds {seeds}: {b['world']}, {b['distance_m']:g} m", "",
             "| scenario | " + " | ".join(run_label(k) for k in variants) + " |",
             "|---|" + "---|" * len(variants)]
    for name, cells in pool.items():
        row = []
        for k in variants:
            c = cells[k]
            bl = c["blind"]
            nees = "–" if bl is None else f"{bl['mean']:.2f} [{bl['interval'][0]:.2f}, {bl['interval'][1]:.2f}] {bl['verdict'][:4]}"
            end = "" if name == FAULT_FREE else f" / end <= 2x {c['goals'].get('end_within_2x', 0)}/{c['seeds']}"
            row.append(nees + end)
        lines.append(f"| {name} | " + " | ".join(row) + " |")
    lines += ["", ("Cells: the seeds' position NEES while blind pooled (ANEES: mean over all samples, 95 % "
                   "interval for the sum of the windows' effective sample sizes) with its verdict / seeds whose "
                   "end RMSE is within 2x their fault-free ATE. The fault-free row pools the nominal window."), ""]
    return "\n".join(lines)


def variants_of(compare_cfg: CompareConfig) -> tuple[str, ...]:
    """The passes a comparison with ``compare_cfg`` makes: each of its back-ends without and with
    relocalization (the table's columns)."""
    return tuple(run_key(b, r) for b in compare_cfg.backends for r in (False, True))


VARIANTS = variants_of(CompareConfig())  # the default comparison's columns (results without "variants")


def _cell(m: dict) -> str:
    if "error" in m:
        return "crash"
    parts = [f"{m['ate_m']:.3f}", f"{m['end_rmse_m']:.3f} ({m['end_ratio']:.1f}x)"]
    if "blind" in m:
        b = m["blind"]
        lo, hi = b["interval"]
        parts.append(f"{b['mean']:.2f} [{lo:.2f}, {hi:.2f}] {b['verdict'][:4]}")
    if "sigma_growth" in m:
        parts.append(f"{m['sigma_growth']:.1f}x")
        parts.append("never" if m["recovery_s"] is None else f"{m['recovery_s']:.0f} s")
    return " / ".join(parts)


def markdown(res: dict) -> str:
    """The fault-scenario table (one row per scenario, one column per variant) and its key."""
    b = res["bench"]
    variants = tuple(res.get("variants", VARIANTS))
    lines = [f"### Fault scenarios: {b['world']}, seed {b['seed']}, {b['distance_m']:g} m", "",
             "| scenario | window [s] | " + " | ".join(run_label(k) for k in variants) + " | goals met |",
             "|---|---|" + "---|" * len(variants) + "---|"]
    for name, entry in res["scenarios"].items():
        w = entry["window_s"]
        win = f"{w[0]:.0f}-{w[1]:.0f}"
        cells = [_cell(entry["runs"][k]) for k in variants]
        if name == FAULT_FREE:
            met = "–"
        else:
            goals = [goals_met(entry["runs"][k]) for k in variants]
            met = ", ".join(f"{g}: {sum(x[g] for x in goals)}/{len(goals)}" for g in goals[0])
        lines.append(f"| {name} | {win} | " + " | ".join(cells) + f" | {met} |")
    lines += ["", ("Cells: ATE m (final estimate) / end RMSE m over the last "
              f"{b['end_window_s']:g} s (x the fault-free online ATE of that variant) / while blind: mean position "
              "NEES (2 dof) [95 % interval for its effective sample size] verdict / position sigma growth over the "
              "window / time after the window until the error stays below 2x the fault-free ATE. The fault-free row "
              f"tests its NEES over the nominal window ({b['start_s']:g} s + {b['duration_s']:g} s). Goals: finished; "
              "consistent while blind; end RMSE <= 2x the fault-free ATE."), ""]
    return "\n".join(lines)

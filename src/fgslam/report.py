"""Tables and JSON of a comparison, in the shape of the reference's Tables III/IV.

Columns are worlds; rows are the traverse (distance, duration), then per variant ATE (RMSE, the
``evo_ape`` figure), ATE max, RPE per 10 m, and the ATE improvement, then fix statistics,
consistency (inside 3 sigma, and the two-sided NEES tests of position, yaw and height with their
95 % intervals, :mod:`fgslam.nees`) and runtime.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def _f(v, fmt: str = "{:.3f}") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return fmt.format(v)


def nees_cell(test: dict) -> str | None:
    """A two-sided NEES test (:meth:`fgslam.nees.NeesTest.to_dict`) as "mean [lo, hi]", with the
    verdict when the mean lies outside the interval."""
    if test.get("mean") is None or not math.isfinite(test["mean"]):
        return None
    lo, hi = test["interval"]
    cell = f"{test['mean']:.2f} [{lo:.2f}, {hi:.2f}]"
    return cell if test["verdict"] == "consistent" else f"{cell} {test['verdict']}"


def _variants(summary: dict) -> list[str]:
    return [k for k in summary["runs"] if k != "dead_reckoning"]


def table_rows(summaries: list[dict]) -> list[tuple[str, list[str]]]:
    """(row label, one cell per world) for the markdown table."""
    from fgslam.compare import run_label

    rows: list[tuple[str, list[str]]] = []

    def row(label, fn, fmt="{:.3f}"):
        cells = []
        for s in summaries:
            try:
                cells.append(_f(fn(s), fmt))
            except (KeyError, TypeError):
                cells.append("–")
        rows.append((label, cells))

    row("Distance [m]", lambda s: s["distance_m"], "{:.2f}")
    row("Duration [s]", lambda s: s["duration_s"], "{:.1f}")
    row("Dead reckoning ATE [m]", lambda s: s["runs"]["dead_reckoning"]["ate"]["rmse"])
    row("Dead reckoning drift [% of distance]", lambda s: s["runs"]["dead_reckoning"]["drift_pct"], "{:.2f}")
    variants = _variants(summaries[0]) if summaries else []
    base = variants[0] if variants else None
    for k in variants:
        lab = run_label(k)
        row(f"{lab} ATE [m]", lambda s, k=k: s["runs"][k]["ate"]["rmse"])
        row(f"{lab} ATE max [m]", lambda s, k=k: s["runs"][k]["ate"]["max"])
        row(f"{lab} ATE planar / height RMSE [m]",
            lambda s, k=k: "{:.3f} / {:.3f}".format(s["runs"][k]["ate_planar"]["rmse"],
                                                   s["runs"][k]["height_error"]["rmse"]), "{}")
        row(f"{lab} RPE/10 m [m]", lambda s, k=k: s["runs"][k]["rpe"]["rmse"])
        row(f"{lab} drift [% of distance]", lambda s, k=k: s["runs"][k]["drift_pct"], "{:.2f}")
        if k.endswith("_reloc"):
            row(f"{lab} ATE improvement [%]", lambda s, k=k: s["runs"][k]["ate_improvement_over_own_pct"], "{:.1f}")
            if base and not k.startswith(base.split("_")[0]):
                row(f"{lab} vs {run_label(base)} ATE improvement [%]",
                    lambda s, k=k: s["runs"][k][f"ate_improvement_over_{base}_pct"], "{:.1f}")
    ref = next((k for k in variants if k.endswith("_reloc")), None)
    if ref:
        fx = lambda s: s["runs"][ref]["fixes"]
        row("Fix attempts", lambda s: fx(s)["attempts"], "{:d}")
        row("Fixes", lambda s: fx(s)["fixes"], "{:d}")
        row("Fix rate [Hz]", lambda s: fx(s)["rate_hz"], "{:.3f}")
        row("Time to first fix (measured / applied) [s]",
            lambda s: "{:.1f} / {:.1f}".format(*s["runs"][ref]["fixes"]["first_fix_s"]), "{}")
        row("Fix position error median [m]", lambda s: fx(s)["position_error_m"]["median"])
        row("Fix position error mean [m]", lambda s: fx(s)["position_error_m"]["mean"])
        row("Fix NEES (x,y,yaw) alone [95 % interval]", lambda s: nees_cell(fx(s).get("nees_alone") or {}), "{}")
        row("Fix NEES (x,y,yaw) as sent, mean", lambda s: fx(s)["nees_mean"], "{:.2f}")
        row("Fix yaw error median [deg]", lambda s: np.degrees(fx(s)["yaw_error_rad"]["median"]), "{:.2f}")
        row("Fix heights from the DEM (n / z RMSE m / NEES)",  # "–" without a terrain model
            lambda s: "{:d} / {:.3f} / {:.2f}".format(fx(s)["heights"]["n"], fx(s)["heights"]["error_rmse_m"],
                                                     fx(s)["heights"]["nees"]), "{}")
        for th in ("0.5", "1", "2"):
            row(f"Fixes within {th} m [%]", lambda s, th=th: 100 * fx(s)["within_m"][th], "{:.1f}")
        for k in variants:
            if k.endswith("_reloc"):
                row(f"Fixes accepted by {run_label(k.split('_')[0])}", lambda s, k=k: s["runs"][k]["fixes"]["accepted"], "{:d}")
    for k in variants:
        row(f"{run_label(k)} inside 3σ [%]", lambda s, k=k: 100 * s["runs"][k]["consistency"]["inside_3sigma"], "{:.1f}")
        for part, dof in (("position", "x,y"), ("yaw", "yaw"), ("height", "z")):  # "–" where a run has none
            row(f"{run_label(k)} NEES ({dof}) [95 % interval]",
                lambda s, k=k, part=part: nees_cell(s["runs"][k]["consistency"].get(part) or {}), "{}")
    for k in variants:
        row(f"{run_label(k)} wall time [s]", lambda s, k=k: s["runs"][k]["runtime"]["wall_s"], "{:.1f}")
    for k in variants:
        row(f"{run_label(k)} update p99 [ms]", lambda s, k=k: s["runs"][k]["runtime"]["update_p99_ms"], "{:.1f}")
    for k in variants:
        row(f"{run_label(k)} frame update CPU p99 [ms]", lambda s, k=k: s["runs"][k]["runtime"]["frame_cpu_p99_ms"],
            "{:.1f}")
    for k in variants:
        row(f"{run_label(k)} peak RSS [MB]", lambda s, k=k: (s["runs"][k]["memory"] or [{}])[-1]["peak_rss_mb"], "{:.0f}")
    for k in variants:
        if k.endswith("_reloc"):
            row(f"{run_label(k)} fixes refused by the smoother window",
                lambda s, k=k: s["runs"][k]["n_fixes_older_than_window"], "{:d}")
    row("Whole comparison wall time [s]", lambda s: s["wall_s"], "{:.1f}")
    row("Whole comparison real-time factor [x]", lambda s: s["real_time_factor"], "{:.1f}")
    return rows


def markdown_table(summaries: list[dict]) -> str:
    """The comparison table (markdown), one column per world."""
    head = "| Metric | " + " | ".join(s["name"] for s in summaries) + " |"
    sep = "| --- | " + " | ".join("---:" for _ in summaries) + " |"
    lines = [head, sep] + [f"| {label} | " + " | ".join(cells) + " |" for label, cells in table_rows(summaries)]
    return "\n".join(lines) + "\n"


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(float(o)) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    return o


def write_results(out_dir: Path, summaries: list[dict], extra: dict | None = None) -> tuple[Path, Path]:
    """Write OUT/table.md and OUT/results.json; returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    table = out_dir / "table.md"
    table.write_text(markdown_table(summaries))
    res = out_dir / "results.json"
    res.write_text(json.dumps(_jsonable({"worlds": summaries, **(extra or {})}), indent=2))
    return table, res

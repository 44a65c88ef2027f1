"""Statistics of a campaign across seeds, per world and variant, and its ``summary.md`` / ``summary.json``.

Every numeric leaf of a task's ``result`` (and of its ``runtime``, under ``runtime.``) is reduced
over the group's successful seeds to mean, median and p90 (numpy's linear percentile); missing
values (a fix error when no fix was made) are left out and ``n`` says how many seeds counted.
Consistency across seeds is the ANEES of each back-end's position, yaw and height: the seeds' NEES pooled
and tested two-sided against the chi-square interval of their summed effective sample sizes
(:func:`fgslam.nees.pooled_test`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from fgslam.campaign.results import clean
from fgslam.nees import NeesTest, Verdict, pooled_test
from fgslam.report import nees_cell

# (dotted metric, label, scale for display) of the rows of summary.md, per world and variant.
SUMMARY_ROWS = [
    ("runs.ekf.ate_rmse_m", "EKF ATE [m]", 1.0),
    ("runs.ekf_reloc.ate_rmse_m", "EKF + reloc ATE [m]", 1.0),
    ("runs.isam2.ate_rmse_m", "iSAM2 ATE [m]", 1.0),
    ("runs.isam2_reloc.ate_rmse_m", "iSAM2 + reloc ATE [m]", 1.0),
    ("runs.ekf_reloc.improvement_over_own_pct", "EKF + reloc improvement over EKF [%]", 1.0),
    ("runs.isam2_reloc.improvement_over_own_pct", "iSAM2 + reloc improvement over iSAM2 [%]", 1.0),
    ("runs.isam2_reloc.improvement_over_baseline_pct", "iSAM2 + reloc improvement over EKF [%]", 1.0),
    ("fixes.rate_hz", "Fix rate [Hz]", 1.0),
    ("fixes.position_error_median_m", "Fix median position error [m]", 1.0),
    ("runs.ekf_reloc.inside_3sigma", "EKF + reloc inside 3-sigma [%]", 100.0),
    ("runs.isam2_reloc.inside_3sigma", "iSAM2 + reloc inside 3-sigma [%]", 100.0),
    ("runs.ekf_reloc.ate_max_m", "EKF + reloc max error [m]", 1.0),
    ("runs.isam2_reloc.ate_max_m", "iSAM2 + reloc max error [m]", 1.0),
    ("runs.ekf.drift_pct", "EKF drift without fixes [% of distance]", 1.0),
    ("runs.isam2.drift_pct", "iSAM2 drift without fixes [% of distance]", 1.0),
    ("runtime.real_time_factor", "Real-time factor (whole comparison)", 1.0),
    ("runtime.runs_update_p99_ms.ekf_reloc", "EKF + reloc update p99 [ms]", 1.0),
    ("runtime.runs_update_p99_ms.isam2_reloc", "iSAM2 + reloc update p99 [ms]", 1.0),
    ("runtime.runs_frame_cpu_p99_ms.ekf_reloc", "EKF + reloc frame update CPU p99 [ms]", 1.0),
    ("runtime.runs_frame_cpu_p99_ms.isam2_reloc", "iSAM2 + reloc frame update CPU p99 [ms]", 1.0),
    ("runtime.peak_rss_mb", "Worker peak RSS [MB]", 1.0),
]
TASK_COLUMNS = [
    ("runs.ekf.ate_rmse_m", "EKF"), ("runs.ekf_reloc.ate_rmse_m", "EKF + reloc"),
    ("runs.isam2.ate_rmse_m", "iSAM2"), ("runs.isam2_reloc.ate_rmse_m", "iSAM2 + reloc"),
    ("fixes.fixes", "fixes"), ("fixes.rate_hz", "fix rate [Hz]"),
    ("fixes.position_error_median_m", "fix err med [m]"), ("runtime.real_time_factor", "RTF"),
]


def flatten(d: dict, prefix: str = "") -> dict[str, float | None]:
    """Numeric leaves of a nested dict by dotted key ({"a": {"b": 1}} -> {"a.b": 1.0}); None kept."""
    out: dict[str, float | None] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        elif v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)):
            out[key] = None if v is None else float(v)
    return out


def task_values(record: dict) -> dict[str, float | None]:
    """The dotted numeric values of one successful record: its result, and its runtime under ``runtime.``."""
    vals = flatten(record.get("result", {}))
    rt = {k: v for k, v in record.get("runtime", {}).items() if k not in ("pid",)}
    vals.update(flatten(rt, "runtime."))
    return vals


def describe(values: list[float | None]) -> dict:
    """mean, median, p90 (linear) and n of the finite values (None when there are none)."""
    x = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if x.size == 0:
        return {"mean": None, "median": None, "p90": None, "n": 0}
    return {"mean": float(x.mean()), "median": float(np.median(x)), "p90": float(np.percentile(x, 90)),
            "n": int(x.size)}


def aggregate(records: list[dict]) -> dict:
    """Summary of task records: per (world, variant) group, seeds ok/failed and every metric's
    :func:`describe` across seeds; plus the failures with their error text."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for rec in records:
        groups.setdefault((rec["world"], rec["variant"]), []).append(rec)
    out_groups = []
    for (world, variant), recs in groups.items():
        ok = sorted((r for r in recs if r.get("status") == "ok"), key=lambda r: r["seed"])
        per_task = [task_values(r) for r in ok]
        keys = sorted({k for v in per_task for k in v})
        out_groups.append({
            "world": world, "variant": variant,
            "seeds_ok": [r["seed"] for r in ok],
            "seeds_failed": sorted(r["seed"] for r in recs if r.get("status") != "ok"),
            "metrics": {k: describe([v.get(k) for v in per_task]) for k in keys},
            "anees": anees(ok),
        })
    failures = [{"key": r["key"], "world": r["world"], "variant": r["variant"], "seed": r["seed"],
                 "error": r.get("error", "")} for r in records if r.get("status") != "ok"]
    return {"n_tasks": len(records), "n_ok": len(records) - len(failures), "n_failed": len(failures),
            "groups": out_groups, "failures": failures}


def anees(records: list[dict]) -> dict[str, dict[str, dict]]:
    """Per run variant (ekf, isam2_reloc, ...) and part (position, yaw): the seeds' NEES pooled
    into one two-sided test (:meth:`fgslam.nees.NeesTest.to_dict`)."""
    out: dict[str, dict[str, dict]] = {}
    runs = sorted({k for r in records for k in r.get("result", {}).get("runs", {})})
    for run in runs:
        for part in ("position", "yaw", "height"):
            tests = []
            for r in records:
                t = r["result"]["runs"].get(run, {}).get(f"nees_{part}")
                if t and t.get("n") and t.get("mean") is not None and t.get("n_eff"):
                    tests.append(NeesTest(t["dof"], t["mean"], t["n"], t["n_eff"], (0.0, 0.0), Verdict.UNTESTED))
            if tests:
                out.setdefault(run, {})[part] = pooled_test(tests).to_dict() | {"seeds": len(tests)}
    return out


def _fmt(v: float | None, scale: float = 1.0) -> str:
    if v is None:
        return "-"
    v = v * scale
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"


def seed_text(seeds: list[int]) -> str:
    """[0, 1, 2, 5] -> "0-2,5"."""
    parts, i = [], 0
    while i < len(seeds):
        j = i
        while j + 1 < len(seeds) and seeds[j + 1] == seeds[j] + 1:
            j += 1
        parts.append(str(seeds[i]) if i == j else f"{seeds[i]}-{seeds[j]}")
        i = j + 1
    return ",".join(parts) or "none"


def summary_markdown(summary: dict, records: list[dict]) -> str:
    """``summary.md``: one table per world and variant (mean / median / p90 across seeds), one row
    per task, and the failures."""
    lines = ["# Campaign summary", "",
             f"{summary['n_tasks']} tasks: {summary['n_ok']} ok, {summary['n_failed']} failed.", ""]
    for g in summary["groups"]:
        lines += [f"## {g['world']} / {g['variant']}", "",
                  f"Seeds ok: {seed_text(g['seeds_ok'])}; failed: {seed_text(g['seeds_failed'])}.", "",
                  "| Metric | mean | median | p90 | n |", "|---|---:|---:|---:|---:|"]
        for key, label, scale in SUMMARY_ROWS:
            d = g["metrics"].get(key)
            if d is None:
                continue
            lines.append(f"| {label} | {_fmt(d['mean'], scale)} | {_fmt(d['median'], scale)} | "
                         f"{_fmt(d['p90'], scale)} | {d['n']} |")
        if g.get("anees"):
            lines += ["", "ANEES across seeds (two-sided 95 % chi-square interval):", "",
                      "| run | position (2 dof) | yaw (1 dof) | height (1 dof) | seeds |", "|---|---|---|---|---:|"]
            for run, parts in g["anees"].items():
                cells = [nees_cell(parts[p]) or "-" if p in parts else "-" for p in ("position", "yaw", "height")]
                seeds = max(parts[p]["seeds"] for p in parts)
                lines.append(f"| {run} | {' | '.join(cells)} | {seeds} |")
        lines.append("")
    lines += ["## Per task (ATE RMSE in metres)", "",
              "| world | variant | seed | " + " | ".join(lab for _, lab in TASK_COLUMNS) + " |",
              "|---|---|---:|" + "---:|" * len(TASK_COLUMNS)]
    for r in sorted((r for r in records if r.get("status") == "ok"), key=lambda r: (r["world"], r["variant"], r["seed"])):
        v = task_values(r)
        cells = [(str(int(v[k])) if k == "fixes.fixes" and v.get(k) is not None else _fmt(v.get(k)))
                 for k, _ in TASK_COLUMNS]
        lines.append(f"| {r['world']} | {r['variant']} | {r['seed']} | " + " | ".join(cells) + " |")
    if summary["failures"]:
        lines += ["", "## Failed tasks", "", "| task | error |", "|---|---|"]
        for f in summary["failures"]:
            err = str(f["error"]).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {f['key']} | {err} |")
    return "\n".join(lines) + "\n"


def write_summary(out_dir: Path, records: list[dict], extra: dict | None = None) -> tuple[Path, Path]:
    """Write ``OUT/summary.md`` and ``OUT/summary.json`` (strict JSON); returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = aggregate(records)
    from fgslam.io.outdir import write_text_atomic

    md = write_text_atomic(out_dir / "summary.md", summary_markdown(summary, records))
    js = write_text_atomic(out_dir / "summary.json", json.dumps(clean({**summary, **(extra or {})}), indent=2, allow_nan=False))
    return md, js

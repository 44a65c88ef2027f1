"""Files of a single run: ``<variant>.tum`` (``ekf.tum``, ``isam2_reloc.tum``, ...), beside it
``ground_truth.tum`` when the run has truth (so that ``evo_ape tum ground_truth.tum ekf.tum``
labels each curve by its variant), ``metrics.json``, ``fixes.csv``, ``config.yaml``; and the same
TUM files per world of a comparison (``<world>/``)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from fgslam import metrics as M
from fgslam.report import _jsonable
from fgslam.runner import RunResult
from reloc.backend import Trajectory

FIX_COLUMNS = [
    "t_meas", "t_recv", "x_m", "y_m", "yaw_rad", "var_x", "var_y", "var_yaw", "cov_xy", "cov_xyaw", "cov_yyaw",
    "n_inliers", "rmse_m", "accepted", "reason", "error_position_m", "error_yaw_rad",
    "z_m", "var_z", "error_z_m",  # the fix's height from the DEM (empty without one)
    "source", "correlation_scale",  # the catalog's landmark kind(s); the producer's correlation factor in the covariance
]


def write_fixes_csv(path: Path, run: RunResult, gt: Trajectory | None) -> Path:
    """One row per fix the back-end received: the fix, its covariance, outcome and (with truth) error."""
    path = Path(path)
    rows = []
    outs = run.outcomes
    if outs and gt is not None:
        t = np.array([o.fix.t_meas for o in outs])
        pos, yaw = M.fix_errors(np.array([o.fix.xyyaw for o in outs]), t, gt)
        z_true = M.interpolate_truth(gt, t)[0][:, 2]
    else:
        pos = yaw = z_true = np.full(len(outs), np.nan)
    for o, ep, ey, zt in zip(outs, pos, yaw, z_true):
        f, C, h = o.fix, o.fix.cov_xyyaw, o.fix.height
        height = ["", "", ""] if h is None else [h.z_m, h.var_m2, h.z_m - zt]
        rows.append([f.t_meas, f.t_recv, f.x_m, f.y_m, f.yaw_rad, C[0, 0], C[1, 1], C[2, 2], C[0, 1], C[0, 2], C[1, 2],
                     f.n_inliers, f.rmse_m, int(o.accepted), o.reason, ep, ey, *height, f.source, f.correlation_scale])
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FIX_COLUMNS)
        for r in rows:
            w.writerow([f"{v:.9g}" if isinstance(v, (float, np.floating)) else v for v in r])
    return path


GROUND_TRUTH_TUM = "ground_truth.tum"


def write_tums(out: Path, runs: dict[str, RunResult], gt: Trajectory | None) -> list[Path]:
    """``<key>.tum`` of every run's final trajectory (keys as :func:`fgslam.compare.run_key`) and
    ``ground_truth.tum`` (with truth) into ``out``; returns their paths."""
    from fgslam.io.tum import write_tum

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for key, run in runs.items():
        paths.append(out / f"{key}.tum")
        write_tum(paths[-1], run.final.t, run.final.T_world_base)
    if gt is not None:
        paths.append(out / GROUND_TRUTH_TUM)
        write_tum(paths[-1], gt.t, gt.T_world_base)
    return paths


def write_run_outputs(out: Path, run: RunResult, gt: Trajectory | None, metrics: dict, config: dict,
                      key: str = "trajectory") -> list[Path]:
    """Write the files of ``fgslam run`` into ``out`` (the trajectory as ``<key>.tum``); returns their paths."""
    import yaml

    out = Path(out)
    tums = write_tums(out, {key: run}, gt)
    met = out / "metrics.json"
    met.write_text(json.dumps(_jsonable(metrics), indent=2))
    fixes = write_fixes_csv(out / "fixes.csv", run, gt)
    cfg = out / "config.yaml"
    cfg.write_text(yaml.safe_dump(_jsonable(config), sort_keys=False))
    return [*tums, met, fixes, cfg]


def write_comparison(out: Path, comparisons: list, config, rrd: bool = True) -> list[Path]:
    """table.md, results.json, PNG plots per world, compare.rrd and config.yaml of a comparison."""
    import yaml

    from fgslam.compare import DR_KEY, resolved_compare_config, resolved_dead_reckoning_config
    from fgslam.report import write_results
    from fgslam.viz.plots import write_plots

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    used = resolved_compare_config(config)  # every back-end's resolved config, not only overrides
    files = list(write_results(out, [wc.metrics for wc in comparisons], {"config": used}))
    for wc in comparisons:
        files += write_plots(out, wc)
        files += write_tums(out / wc.inputs.name, {**wc.runs, DR_KEY: wc.dr}, wc.gt)
    if rrd:
        from fgslam.viz.rerun_log import write_comparison_rrd

        files.append(write_comparison_rrd(out / "compare.rrd", comparisons))
    cfg = out / "config.yaml"
    cfg.write_text(yaml.safe_dump(_jsonable({"config": used, "dead_reckoning": resolved_dead_reckoning_config(),
                                             "inputs": [wc.inputs.source for wc in comparisons]}), sort_keys=False))
    files.append(cfg)
    return files

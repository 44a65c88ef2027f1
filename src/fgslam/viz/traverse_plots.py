"""Figures for long traverses, where a whole-world XY plot hides every difference that matters.

- error against distance travelled, every variant (and dead reckoning) on one logarithmic axis,
  with the fixes as a rug and each variant's drift (final error as % of distance) in the legend;
- the XY track of each back-end with relocalization coloured by its position error, with zooms on
  its worst stretch and on its end, where the estimates' differences are visible.

Both use the final trajectory (``RunResult.final``, the one the ATE is computed on) and the truth's
travelled distance at each stamp.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgslam import metrics as M
from fgslam.metrics import drift_pct, error_along
from fgslam.viz.plots import COLORS, _plt


def plot_error_vs_distance(path: Path, wc) -> Path:
    """Position error against distance travelled for every variant on one log axis (one PNG)."""
    from fgslam.compare import run_label

    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 4.8))
    d_gt = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(wc.gt.positions_m[:, :2], axis=0), axis=1))])
    for key, run in [("dr", wc.dr)] + list(wc.runs.items()):
        if len(run.final) < 2:
            continue
        dist, err = error_along(run.final, wc.gt)
        name = key.split("_")[0]
        style = "-" if key.endswith("_reloc") else ("--" if key != "dr" else ":")
        label = "Dead reckoning" if key == "dr" else run_label(key)
        ax.plot(dist, np.maximum(err, 1e-4), color=COLORS.get(name, "k"), ls=style, lw=1.1,
                label=f"{label} (drift {drift_pct(run.final, wc.gt):.2f} %)")
    fix_t = np.array([a.fix.t_meas for a in wc.attempts if a.fix is not None])
    if fix_t.size:
        ax.plot(np.interp(fix_t, wc.gt.t, d_gt), np.full(fix_t.size, 1.2e-4), "|", color=COLORS["fix"], ms=8,
                label=f"fixes ({fix_t.size})")
    ax.set_yscale("log")
    ax.set_xlabel("distance travelled [m]")
    ax.set_ylabel("position error x/y [m]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    ax.set_title(f"{wc.inputs.name}: error against distance")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_xy_error(path: Path, wc, zoom_half_m: float = 15.0) -> Path:
    """XY track of each back-end with relocalization coloured by its position error, over truth and
    dead reckoning; beside it two zooms (its worst error, its end) of +-``zoom_half_m`` (at most a
    tenth of the track's extent), framed on the whole track. One row per back-end, one PNG."""
    plt = _plt()
    from matplotlib.collections import LineCollection
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    from fgslam.compare import run_label

    keys = [k for k in wc.runs if k.endswith("_reloc")] or list(wc.runs)
    errs = {k: error_along(wc.runs[k].final, wc.gt)[1] for k in keys}
    all_err = np.concatenate([e for e in errs.values() if e.size] or [np.ones(1)])
    norm = LogNorm(vmin=max(np.percentile(all_err, 1), 1e-3), vmax=max(all_err.max(), 2e-3))
    span = np.ptp(wc.gt.positions_m[:, :2], axis=0).max()
    half = max(min(zoom_half_m, 0.1 * span), 0.5)
    fig, axes = plt.subplots(len(keys), 3, figsize=(15, 5.2 * len(keys)), squeeze=False,
                             gridspec_kw={"width_ratios": [2, 1, 1]})
    for row, key in zip(axes, keys):
        run = wc.runs[key]
        _, _, inside = M.interpolate_truth(wc.gt, run.final.t)
        p, err = run.final.positions_m[inside, :2], errs[key]
        segs = np.stack([p[:-1], p[1:]], axis=1)
        centres = [("worst error", p[int(np.argmax(err))]), ("end", p[-1])] if len(p) else []
        for ax, scale in zip(row, (1.0, 1.6, 1.6)):
            ax.plot(*wc.gt.positions_m[:, :2].T, color=COLORS["truth"], lw=2.5 * scale, alpha=0.5, label="truth")
            ax.plot(*wc.dr.final.positions_m[:, :2].T, color=COLORS["dr"], lw=scale, ls=":", label="dead reckoning")
            lc = LineCollection(segs, cmap="viridis", norm=norm, lw=1.8 * scale)
            lc.set_array(0.5 * (err[:-1] + err[1:]))
            ax.add_collection(lc)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel("x [m] (world)")
        row[0].autoscale_view()
        row[0].set_ylabel("y [m]")
        row[0].set_title(f"{wc.inputs.name}: {run_label(key)}, ATE {np.sqrt(np.mean(err**2)):.3f} m")
        row[0].legend(fontsize=7, loc="best")
        for ax, (label, c) in zip(row[1:], centres):
            ax.set_xlim(c[0] - half, c[0] + half)
            ax.set_ylim(c[1] - half, c[1] + half)
            ax.set_title(f"{label} (±{half:.3g} m)", fontsize=9)
            row[0].add_patch(Rectangle(c - half, 2 * half, 2 * half, fill=False, ec="k", lw=0.8))
            row[0].annotate(label, c + half, fontsize=7)
        fig.colorbar(lc, ax=list(row), shrink=0.85, label="position error [m]")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_traverse_plots(out_dir: Path, wc) -> list[Path]:
    """``<world>_error_vs_distance.png`` and ``<world>_xy_error.png`` (needs ground truth)."""
    if wc.gt is None:
        return []
    out_dir = Path(out_dir)
    n = wc.inputs.name
    return [plot_error_vs_distance(out_dir / f"{n}_error_vs_distance.png", wc),
            plot_xy_error(out_dir / f"{n}_xy_error.png", wc)]

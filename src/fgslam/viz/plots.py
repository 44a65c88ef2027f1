"""Matplotlib figures of a comparison (Agg backend, written as PNG files).

- XY trajectories over the orbital image: truth, dead reckoning, each back-end with and without
  relocalization, fix events;
- position error with its 3-sigma envelope per back-end (sqrt of the largest eigenvalue of the
  x/y covariance), with and without relocalization;
- fix error distributions (position and yaw).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgslam import metrics as M

COLORS = {"truth": "#2ca02c", "dr": "#7f7f7f", "ekf": "#1f77b4", "isam2": "#d62728", "fix": "#ff7f0e"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _background(ax, wc) -> None:
    inp = wc.inputs
    if inp.orbital_image is not None and inp.orbital_extent is not None:
        ax.imshow(inp.orbital_image, extent=inp.orbital_extent, origin="upper", cmap="gray", alpha=0.8)
    for i, (kind, cat) in enumerate(inp.catalogs.items()):  # every landmark kind's catalog
        ax.scatter(cat.xy_m[:, 0], cat.xy_m[:, 1], s=4, c="#e0c080" if i == 0 else f"C{i + 4}", marker=".",
                   label=f"{kind} catalog", zorder=2)


def plot_xy(path: Path, wc) -> Path:
    """XY trajectories per back-end side by side over the orbital image (one PNG)."""
    plt = _plt()
    names = sorted({k.split("_")[0] for k in wc.runs}, key=list(COLORS).index)
    fig, axes = plt.subplots(1, len(names), figsize=(6.5 * len(names), 6.2), squeeze=False)
    fixes = np.array([a.fix.xyyaw for a in wc.attempts if a.fix is not None]).reshape(-1, 3)
    for ax, name in zip(axes[0], names):
        _background(ax, wc)
        if wc.gt is not None:
            ax.plot(*wc.gt.positions_m[:, :2].T, color=COLORS["truth"], lw=2, label="truth", zorder=3)
        ax.plot(*wc.dr.final.positions_m[:, :2].T, color=COLORS["dr"], lw=1, ls=":", label="dead reckoning", zorder=3)
        from fgslam.compare import run_label

        for key, ls in ((name, "--"), (f"{name}_reloc", "-")):
            if key in wc.runs:
                ax.plot(*wc.runs[key].final.positions_m[:, :2].T, color=COLORS.get(name, "k"), ls=ls, lw=1.0,
                        label=run_label(key), zorder=4)
        if len(fixes):
            ax.scatter(fixes[:, 0], fixes[:, 1], s=5, marker="o", c=COLORS["fix"], alpha=0.6, lw=0,
                       label=f"fixes ({len(fixes)})", zorder=2.5)
        p = wc.gt.positions_m if wc.gt is not None else wc.dr.final.positions_m
        pad = 4.0
        ax.set_xlim(p[:, 0].min() - pad, p[:, 0].max() + pad)
        ax.set_ylim(p[:, 1].min() - pad, p[:, 1].max() + pad)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (world)")
        ax.set_ylabel("y [m]")
        ax.set_title(f"{wc.inputs.name}: {M_label(name)}")
        ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def M_label(name: str) -> str:
    from fgslam.compare import LABELS

    return LABELS.get(name, name)


def plot_errors(path: Path, wc) -> Path:
    """Position error and 3-sigma envelope over time, one panel per variant (one PNG)."""
    plt = _plt()
    from fgslam.compare import run_label

    keys = list(wc.runs)
    fig, axes = plt.subplots(2, (len(keys) + 1) // 2, figsize=(12, 6.5), squeeze=False, sharex=True)
    fix_t = [a.fix.t_recv for a in wc.attempts if a.fix is not None]
    for ax, key in zip(axes.T.ravel(), keys):
        run = wc.runs[key]
        if wc.gt is None or len(run.online) == 0:
            ax.set_visible(False)
            continue
        _, s = M.consistency(run.online, wc.gt)
        P = run.online.cov[:, :2, :2]
        t_in = s["t"]
        mask = np.isin(run.online.t, t_in)
        lam = np.linalg.eigvalsh(P[mask])[:, -1]
        err = np.linalg.norm(s["err_xy"], axis=1)
        color = COLORS.get(key.split("_")[0], "k")
        ax.plot(t_in - t_in[0], err, color=color, lw=1, label="|error| x/y")
        ax.plot(t_in - t_in[0], 3 * np.sqrt(lam), color="k", ls="--", lw=0.8, label="3σ")
        if key.endswith("_reloc") and fix_t:
            ax.plot(np.asarray(fix_t) - t_in[0], np.zeros(len(fix_t)), "|", color=COLORS["fix"], ms=6,
                    label="fix received")
        ax.set_title(run_label(key), fontsize=10)
        ax.set_ylabel("m")
        ax.legend(fontsize=7, loc="upper left")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{wc.inputs.name}: position error and 3σ envelope")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_fix_errors(path: Path, wc) -> Path:
    """Histograms of fix position error (m) and yaw error (deg) against truth at t_meas."""
    plt = _plt()
    fixes = [a.fix for a in wc.attempts if a.fix is not None]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    if fixes and wc.gt is not None:
        pos, yaw = M.fix_errors(np.array([f.xyyaw for f in fixes]), np.array([f.t_meas for f in fixes]), wc.gt)
        a1.hist(pos, bins=min(30, max(5, len(pos) // 2)), color=COLORS["fix"])
        a1.axvline(np.median(pos), color="k", ls="--", label=f"median {np.median(pos):.3f} m")
        a2.hist(np.degrees(yaw), bins=min(30, max(5, len(yaw) // 2)), color=COLORS["fix"])
        a1.legend(fontsize=8)
    else:
        a1.text(0.5, 0.5, "no fixes", ha="center", transform=a1.transAxes)
    a1.set_xlabel("fix position error [m]")
    a2.set_xlabel("fix yaw error [deg]")
    a1.set_ylabel("fixes")
    fig.suptitle(f"{wc.inputs.name}: {len(fixes)} fixes")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_plots(out_dir: Path, wc) -> list[Path]:
    """All PNGs of one world comparison, named ``<world>_{xy,errors,fix_errors}.png``, and the
long-traverse figures of :mod:`fgslam.viz.traverse_plots`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    from fgslam.viz.traverse_plots import write_traverse_plots

    n = wc.inputs.name
    return [
        plot_xy(out_dir / f"{n}_xy.png", wc),
        plot_errors(out_dir / f"{n}_errors.png", wc),
        plot_fix_errors(out_dir / f"{n}_fix_errors.png", wc),
        *write_traverse_plots(out_dir, wc),
    ]

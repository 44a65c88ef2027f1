"""Benchmarks of the kilometre worlds (tables and plots for docs/sim.md).

    python -m sim.tiled.bench memory --world plains-2km --distance-m 10000 --every-m 500 --out DIR
        simulate (streaming) and sample the resident memory along the drive: DIR/memory.csv and
        a markdown table (distance, RSS now, peak RSS, CPU and wall time so far)
    python -m sim.tiled.bench table DIR [DIR ...]
        the preset table from the world.yaml of ``fgslam sim`` directories
    python -m sim.tiled.bench sfd DIR [DIR ...] --out docs/img
        simulated against model size-frequency of craters (every crater of the world) and rocks
        (the tiles along the route), one PNG per directory
    python -m sim.tiled.bench drift SIMDIR RUNDIR [RUNDIR ...]
        the drift table of ``fgslam run`` outputs (their ``<variant>.tum`` and metrics.json)
        against the bag's own ground truth: distance, final and maximum horizontal error (m, and
        the final as % of the distance driven), ATE, position NEES with its two-sided interval,
        real-time factor, update p99 and peak RSS
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("sim.tiled.bench")


def _load(d: Path) -> dict:
    import yaml

    return yaml.safe_load((Path(d) / "world.yaml").read_text())


def memory(world: str, seed: int, distance_m: float, every_m: float, out: Path) -> list[dict]:
    from sim.tiled.outputs import simulate_to_bag
    from sim.tiled.presets import preset_config
    from sim.tiled.stream import cpu_s, peak_rss_mb, rss_mb

    rows: list[dict] = []
    t0, c0 = time.perf_counter(), cpu_s()
    nxt = [every_m]

    def progress(stage: str, done: float, total: float) -> None:
        if stage == "drive" and done >= nxt[0]:
            rows.append({"distance_m": done, "rss_mb": rss_mb(), "peak_rss_mb": peak_rss_mb(),
                         "cpu_s": cpu_s() - c0, "wall_s": time.perf_counter() - t0})
            nxt[0] += every_m

    run = simulate_to_bag(preset_config(world, seed, {"traverse": {"distance_m": distance_m}}), out, progress=progress)
    s = run.stats
    rows.append({"distance_m": s["distance_m"], "rss_mb": rss_mb(), "peak_rss_mb": peak_rss_mb(),
                 "cpu_s": cpu_s() - c0, "wall_s": time.perf_counter() - t0, "stage": "with orbital products"})
    with open(Path(out) / "memory.csv", "w") as f:
        f.write("distance_m,rss_mb,peak_rss_mb,cpu_s,wall_s\n")
        f.writelines(f"{r['distance_m']:.1f},{r['rss_mb']:.1f},{r['peak_rss_mb']:.1f},{r['cpu_s']:.1f},{r['wall_s']:.1f}\n" for r in rows)
    print("| distance (m) | RSS now (MB) | peak RSS (MB) | CPU (s) | wall (s) |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        tag = f" ({r['stage']})" if "stage" in r else ""
        print(f"| {r['distance_m']:.0f}{tag} | {r['rss_mb']:.0f} | {r['peak_rss_mb']:.0f} | {r['cpu_s']:.0f} | {r['wall_s']:.0f} |")
    return rows


def table(dirs: list[Path]) -> None:
    print("| preset | world | rocks k | craters (world / in coverage / catalog) | rock catalog | traverse | duration "
          "| mean speed | bag | CPU (one core) | x real time (CPU / wall) | peak RSS |")
    print("|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for d in dirs:
        w = _load(d)
        s, t = w["stats"], w["config"]["tiled"]
        print(f"| {w['world']} | {t['size_m'] / 1000:.2f} km, {t['craters']['age_gyr']} Gyr | {t['rocks']['k']:.0%} "
              f"| {s['n_craters_true']} / {s['n_craters_in_coverage']} / {s['n_craters_catalog']} | {s['n_catalog']} "
              f"| {s['distance_m'] / 1000:.2f} km | {s['duration_s'] / 3600:.2f} h | {s['mean_speed_mps']:.3f} m/s "
              f"| {s['bag_bytes'] / 1e6:.0f} MB | {s['cpu_s']:.0f} s | {s['real_time_factor_cpu']:.0f} / {s['real_time_factor']:.0f} "
              f"| {s['peak_rss_mb']:.0f} MB |")


def sfd(dirs: list[Path], out: Path, n_tiles: int = 12) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from reloc.config import config_from_dict
    from sim.config import SimConfig
    from sim.craters import CraterSFD
    from sim.tiled.presets import resolve_tiled_config
    from sim.tiled.world import TiledWorld

    out.mkdir(parents=True, exist_ok=True)
    for d in dirs:
        w = _load(d)
        cfg = resolve_tiled_config(config_from_dict(SimConfig, w["config"]))
        world = TiledWorld(cfg.world, cfg.seed, cfg.tiled)
        fig, (ax_c, ax_r) = plt.subplots(1, 2, figsize=(11, 4.2))
        # craters: every crater of the world against the model
        truth = np.genfromtxt(Path(d) / "craters_true.csv", delimiter=",", names=True)
        area_km2 = (cfg.tiled.size_m / 1000.0) ** 2
        dd = np.sort(truth["diameter"])[::-1]
        ax_c.loglog(dd, np.arange(1, len(dd) + 1) / area_km2, "k.", ms=2, label=f"simulated ({len(dd)} craters)")
        grid = np.geomspace(cfg.tiled.craters.min_diameter_m, cfg.tiled.craters.max_diameter_m * 0.999, 200)
        model = world.sfd
        ax_c.loglog(grid, model.cumulative_per_m2(grid) * 1e6, "r-", label="model (production, equilibrium cap)")
        prod = CraterSFD(model.age_gyr, model.production, False, model.d_min_m, model.d_max_m)
        ax_c.loglog(grid, prod.cumulative_per_m2(grid) * 1e6, "r:", label=f"Hartmann (2005) production, {model.age_gyr} Gyr")
        ax_c.set(xlabel="rim diameter D (m)", ylabel="N(>D) per km$^2$", title=f"{cfg.world}: craters")
        ax_c.legend(fontsize=8)
        # rocks: tiles along the route
        route = np.array(w["route"])
        s = np.linspace(0, 1, n_tiles)
        seg = np.cumsum(np.r_[0, np.linalg.norm(np.diff(route, axis=0), axis=1)])
        pts = np.column_stack([np.interp(s * seg[-1], seg, route[:, 0]), np.interp(s * seg[-1], seg, route[:, 1])])
        keys = sorted({(world.tile_index(x), world.tile_index(y)) for x, y in pts})
        rocks = [world.tile(*k).rocks for k in keys]
        area = len(keys) * cfg.tiled.tile_size_m**2
        bg = np.sort(np.concatenate([r.diameter_m[~r.ejecta] for r in rocks]))[::-1]
        allr = np.sort(np.concatenate([r.diameter_m for r in rocks]))[::-1]
        ax_r.semilogy(bg, np.arange(1, len(bg) + 1) / area, "k.", ms=2, label=f"simulated background ({len(bg)})")
        if len(allr) > len(bg):
            ax_r.semilogy(allr, np.arange(1, len(allr) + 1) / area, "b.", ms=1, alpha=0.5, label="with ejecta blocks")
        g = np.linspace(cfg.tiled.rocks.min_diameter_m, cfg.tiled.rocks.max_diameter_m * 0.999, 200)
        ax_r.semilogy(g, world.rock_model.cumulative_number(g), "r-",
                      label=f"Golombek & Rapp, k = {cfg.tiled.rocks.k:.0%}")
        det = cfg.sensors.orbital
        ax_r.axvline(det.min_size_px * det.gsd_m, color="g", ls="--", lw=1, label=f"{det.min_size_px:g} px at {det.gsd_m} m/px")
        ax_r.set(xlabel="rock diameter D (m)", ylabel="N(>D) per m$^2$", title=f"{cfg.world}: rocks ({len(keys)} tiles on the route)")
        ax_r.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"sfd_{cfg.world}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        print(f"wrote {path}")


def _ground_truth_xy(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    from rosbags.highlevel import AnyReader

    from reloc.bag_spec import typestore

    t, xy = [], []
    with AnyReader([bag], default_typestore=typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == "/ground_truth"]
        for conn, t_ns, raw in reader.messages(connections=conns):
            p = reader.deserialize(raw, conn.msgtype).pose.pose.position
            t.append(t_ns * 1e-9)
            xy.append((p.x, p.y))
    return np.array(t), np.array(xy)


def _run_track(run_dir: Path) -> np.ndarray:
    """The (N, 8) TUM rows of the one ``<variant>.tum`` an ``fgslam run`` directory holds."""
    tums = [p for p in sorted(Path(run_dir).glob("*.tum")) if p.name != "ground_truth.tum"]
    if len(tums) != 1:
        raise SystemExit(f"{run_dir}: expected one <variant>.tum beside ground_truth.tum, found "
                         f"{[p.name for p in tums] or 'none'}")
    return np.loadtxt(tums[0], ndmin=2)


def drift_rows(sim_dir: Path, runs: list[Path]) -> list[dict]:
    """Per run directory: its variant, the distance driven to its last pose, the final and
    maximum horizontal error against the bag's ground truth (interpolated at the run's poses),
    and figures from its metrics.json."""
    import json

    t_gt, xy_gt = _ground_truth_xy(Path(sim_dir) / "bag")
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy_gt, axis=0), axis=1))])
    rows = []
    for r in runs:
        est = _run_track(r)
        m = json.loads((Path(r) / "metrics.json").read_text())
        inside = (est[:, 0] >= t_gt[0]) & (est[:, 0] <= t_gt[-1])
        est = est[inside]
        gt = np.column_stack([np.interp(est[:, 0], t_gt, xy_gt[:, k]) for k in range(2)])
        err = np.linalg.norm(est[:, 1:3] - gt, axis=1)
        d_end = float(np.interp(est[-1, 0], t_gt, dist))
        pos = m.get("consistency", {}).get("position", {})
        rows.append({
            "run": Path(r).name, "backend": m["backend"], "distance_m": d_end, "final_error_m": float(err[-1]),
            "drift_pct": 100.0 * float(err[-1]) / d_end, "max_error_m": float(err.max()),
            "ate_m": m["ate"]["rmse"], "nees_xy": pos.get("mean"), "nees_interval": pos.get("interval"),
            "nees_verdict": pos.get("verdict"), "real_time_factor": m["runtime"]["real_time_factor"],
            "update_p99_ms": m["runtime"].get("update_p99_ms"),
            "peak_rss_mb": max((row["peak_rss_mb"] for row in m.get("memory", [])), default=float("nan")),
        })
    return rows


def drift(sim_dir: Path, runs: list[Path]) -> None:
    print("| run | back-end | distance | final error m (% of distance) | max error m | ATE RMSE m | "
          "NEES(x,y) [95 %] | x real time | update p99 ms | peak RSS MB |")
    print("|---|---|---:|---:|---:|---:|---|---:|---:|---:|")
    for r in drift_rows(sim_dir, runs):
        lo, hi = r["nees_interval"] or (float("nan"), float("nan"))
        nees = f"{r['nees_xy']:.2f} [{lo:.2f}, {hi:.2f}] {r['nees_verdict']}" if r["nees_xy"] is not None else "-"
        print(f"| {r['run']} | {r['backend']} | {r['distance_m'] / 1000:.2f} km | {r['final_error_m']:.2f} "
              f"({r['drift_pct']:.2f} %) | {r['max_error_m']:.2f} | {r['ate_m']:.2f} | {nees} | "
              f"{r['real_time_factor']:.1f} | {r['update_p99_ms'] or float('nan'):.1f} | {r['peak_rss_mb']:.0f} |")


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    ap = argparse.ArgumentParser(prog="python -m sim.tiled.bench", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("memory")
    m.add_argument("--world", default="plains-2km")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--distance-m", type=float, default=10000.0)
    m.add_argument("--every-m", type=float, default=500.0)
    m.add_argument("--out", type=Path, required=True)
    t = sub.add_parser("table")
    t.add_argument("dirs", type=Path, nargs="+")
    f = sub.add_parser("sfd")
    f.add_argument("dirs", type=Path, nargs="+")
    f.add_argument("--out", type=Path, default=Path("docs/img"))
    r = sub.add_parser("drift")
    r.add_argument("sim_dir", type=Path)
    r.add_argument("runs", type=Path, nargs="+")
    a = ap.parse_args(argv)
    if a.cmd == "memory":
        memory(a.world, a.seed, a.distance_m, a.every_m, a.out)
    elif a.cmd == "table":
        table(a.dirs)
    elif a.cmd == "drift":
        drift(a.sim_dir, a.runs)
    else:
        sfd(a.dirs, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

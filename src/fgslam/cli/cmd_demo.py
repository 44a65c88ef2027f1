"""``fgslam demo``: simulate the default world and compare EKF and iSAM2 on it (the README's main job)."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from fgslam.cli.app import app


@app.command("demo")
def demo_cmd(
    world: str = typer.Option("my2021", "--world", help="World preset: my2020, my2021, my2022, cnes."),
    seed: int = typer.Option(0, "--seed", help="Simulator seed."),
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output directory."),
    distance_m: float | None = typer.Option(None, "--distance-m", help="Traverse length in metres (default: the preset's)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the comparison config."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
) -> None:
    """Simulate WORLD, run EKF and iSAM2 with and without relocalization, print the table, write plots and compare.rrd."""
    from rich.console import Console

    from fgslam.cli.cmd_compare import compare_and_write
    from fgslam.cli.cmd_run import load_config
    from fgslam.inputs import from_sim_run
    from fgslam.io.outdir import OutputDir
    from sim.config import SimConfig
    from sim.simulate import simulate

    console = Console(stderr=True)
    cfg = load_config(config)
    t0 = time.perf_counter()
    sim_cfg = SimConfig(world=world, seed=seed)
    if distance_m is not None:
        import dataclasses

        sim_cfg = dataclasses.replace(sim_cfg, traverse=dataclasses.replace(sim_cfg.traverse, distance_m=distance_m))
    with OutputDir(out, "compare", force=force) as od:  # checked, created and locked before any work
        with console.status(f"simulating {world} (seed {seed})"):
            run = simulate(sim_cfg)
            inputs = from_sim_run(run, name=world)
        console.print(f"simulated {world} in {time.perf_counter() - t0:.1f} s")
        compare_and_write([inputs], od, cfg, console)
    console.print(f"demo done in {time.perf_counter() - t0:.1f} s; open the recording with: rerun {out / 'compare.rrd'}")

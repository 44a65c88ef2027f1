"""``fgslam demo``: simulate a traverse and compare EKF and iSAM2 on it (the README's main job).

By default the first DEMO_DISTANCE_M metres of the rocky-1km preset (seed 0), streamed to a bag in
the output directory: a traverse that never comes back, long enough for SLAM alone to drift
visibly (EKF and iSAM2 end decimetres to metres off) and for the crater fixes to bound it, in a
few minutes on 2 cores. Any kilometre preset (``--world plains-2km``, ``--distance-m``) or yard
(``--world my2021``: the reference paper's setting, rock fixes at ~0.4 Hz, simulated in memory)
can be asked for."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from fgslam.cli.app import app

DEMO_WORLD = "rocky-1km"
# on a kilometre preset, when --distance-m is not given. rocky-1km seed 0, 2 cores, unloaded
# (2026-12-06): 250 m in 4 min 38 s with the set-up check and the simulation (EKF 0.40 m -> 0.11 m
# with fixes, iSAM2 0.46 -> 0.07, 208 fixes, first at 10 s); a slower day, back to back: 4:59 then
# 5:12 with iSAM2's re-placement by place (iSAM2 + reloc 0.064 m); the next, 4:51 then 4:56 with
# the smoother's association error model (iSAM2 0.518 -> 0.333 m); README, "What the demo shows"
DEMO_DISTANCE_M = 250.0


@app.command("demo")
def demo_cmd(
    world: str = typer.Option(DEMO_WORLD, "--world", help="World: a yard (my2020, my2021, my2022, cnes) or a "
                              "kilometre preset (plains-2km, rocky-1km, cratered-3km, sparse-5km)."),
    seed: int = typer.Option(0, "--seed", help="Simulator seed."),
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output directory."),
    distance_m: float | None = typer.Option(None, "--distance-m", help="Traverse length in metres (default: "
                                            f"{DEMO_DISTANCE_M:.0f} on a kilometre preset, a yard's own)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the comparison config "
                                       "(default on a kilometre preset: the simulator's backend.yaml)."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
) -> None:
    """Simulate WORLD, run EKF and iSAM2 with and without relocalization, print the table, write plots and compare.rrd."""
    from rich.console import Console

    from fgslam.cli.cmd_compare import compare_and_write
    from fgslam.cli.cmd_run import load_config
    from fgslam.io.outdir import OutputDir
    from sim.tiled.presets import is_tiled

    console = Console(stderr=True)
    t0 = time.perf_counter()
    with OutputDir(out, "compare", force=force) as od:  # checked, created and locked before any work
        if is_tiled(world):
            inputs, cfg = _orbital_inputs(world, seed, distance_m or DEMO_DISTANCE_M, config, od.staging / "sim", console)
        else:
            inputs, cfg = _yard_inputs(world, seed, distance_m, console), load_config(config)
        console.print(f"simulated {world} in {time.perf_counter() - t0:.1f} s")
        compare_and_write([inputs], od, cfg, console)
    console.print(f"demo done in {time.perf_counter() - t0:.1f} s; open the recording with: rerun {out / 'compare.rrd'}")


def _yard_inputs(world: str, seed: int, distance_m: float | None, console):
    """A yard simulated in memory."""
    import dataclasses

    from fgslam.inputs import from_sim_run
    from sim.config import SimConfig
    from sim.simulate import simulate

    sim_cfg = SimConfig(world=world, seed=seed)
    if distance_m is not None:
        sim_cfg = dataclasses.replace(sim_cfg, traverse=dataclasses.replace(sim_cfg.traverse, distance_m=distance_m))
    with console.status(f"simulating {world} (seed {seed})"):
        return from_sim_run(simulate(sim_cfg), name=world)


def _orbital_inputs(world: str, seed: int, distance_m: float, config: Path | None, sim_dir: Path, console):
    """A kilometre preset streamed to a bag in ``sim_dir`` (part of the demo's output), read back
    (while a forked process writes the orbital products: the two took 8 s each, one after the
    other); the comparison config is ``config`` or the run's backend.yaml."""
    from fgslam.cli.cmd_run import load_config
    from fgslam.cli.cmd_sim import load_sim_config
    from fgslam.inputs import load_sim_dir, read_bag_measurements
    from fgslam.lifetime import Forked
    from sim.tiled.outputs import simulate_to_bag

    read = {}

    def products_beside_the_read(write):
        products = Forked(write, "writing the orbital products")
        try:
            read["bag"] = read_bag_measurements(sim_dir / "bag")
        except BaseException:
            products.kill()
            raise
        return products.result()

    sim_cfg = load_sim_config(world, seed, distance_m, None)
    with console.status(f"simulating {world} (seed {seed}, {distance_m:.0f} m)"):
        simulate_to_bag(sim_cfg, sim_dir, overwrite=False, write_products=products_beside_the_read)
    name = f"{world}-{distance_m:.0f}m"
    inputs = load_sim_dir(sim_dir, preread=read["bag"])
    inputs.name = name
    return inputs, load_config(config if config is not None else sim_dir / "backend.yaml")

"""``fgslam bench e2e``: one world with statistical and with image detections through EKF and iSAM2."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("e2e")
def bench_e2e_cmd(
    world: str = typer.Option("my2021", "--world", help="World preset (my2020, my2021, my2022, cnes) or a Gazebo model directory."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random process of the run."),
    distance_m: float = typer.Option(30.0, "--distance-m", help="Traverse length in metres."),
    stereo_rate_hz: float = typer.Option(
        0.5, "--stereo-rate-hz", help="Stereo frame rate of both sources (the image path renders every frame)."),
    out: Path = typer.Option(..., "--out", help="Output directory (table.md, results.json, statistical/, image/, compare/)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the simulator config."),
    compare_config: Path | None = typer.Option(None, "--compare-config", help="YAML overrides of the comparison config."),
    rrd: bool = typer.Option(False, "--rrd/--no-rrd", help="Also write compare/compare.rrd (rerun)."),
) -> None:
    """Simulate one traverse, run it with statistical and with image detections through EKF and
    iSAM2 (each with and without relocalization) and print the two side by side."""
    import contextlib
    import dataclasses

    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from fgslam.bench.e2e import run_e2e, table_rows
    from fgslam.cli.bench_output import check_out, print_tables
    from fgslam.cli.cmd_run import load_config
    from fgslam.cli.cmd_sim import load_sim_config
    from fgslam.cli.progress import StreamProgress
    from sim.config import validate
    from sim.world import PRESETS

    if world not in PRESETS and not Path(world).is_dir():
        raise typer.BadParameter(f"unknown world {world!r}: use one of {sorted(PRESETS)} or a Gazebo model directory",
                                 param_hint="--world")
    if not distance_m > 0:
        raise typer.BadParameter(f"must be > 0, got {distance_m}", param_hint="--distance-m")
    if not stereo_rate_hz > 0:
        raise typer.BadParameter(f"must be > 0, got {stereo_rate_hz}", param_hint="--stereo-rate-hz")
    check_out(out)  # a file, or not writable: refused before the simulation
    sim_cfg = load_sim_config(world, seed, distance_m, config)
    sensors = sim_cfg.sensors
    sim_cfg = dataclasses.replace(sim_cfg, sensors=dataclasses.replace(
        sensors, stereo=dataclasses.replace(sensors.stereo, rate_hz=stereo_rate_hz)))
    validate(sim_cfg)
    cmp_cfg = load_config(compare_config)  # both configs checked before any long work
    err = Console(stderr=True)
    with Progress(TextColumn("{task.description:<48}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TimeElapsedColumn(), console=err) as progress:

        def tick(name: str, total: int):
            task = progress.add_task(name, total=max(total, 1))
            return lambda: progress.advance(task)

        @contextlib.contextmanager
        def compare_progress(inputs):
            from fgslam.inputs import stream_span_s

            bars = StreamProgress(progress, *stream_span_s(inputs))
            yield lambda stage, t_s: bars.update(f"{inputs.name}: {stage}", t_s)

        res = run_e2e(sim_cfg, out, cmp_cfg, tick=tick, compare_progress=compare_progress, rrd=rrd)
    cols, rows = table_rows(res)
    print_tables([(f"{res['world']}, seed {res['seed']}: statistical vs image detections", cols, rows)], width=100)
    err.print(f"wrote {out / 'table.md'}, {out / 'results.json'}, {out / 'compare'}")

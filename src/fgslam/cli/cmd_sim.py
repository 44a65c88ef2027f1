"""``fgslam sim``: simulate a traverse in a Mars yard and write its bag, catalog and world files."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


def load_sim_config(world: str, seed: int, distance_m: float | None, config: Path | None):
    """The :class:`sim.SimConfig` from defaults, an optional YAML file, then the command-line options."""
    import dataclasses

    import yaml

    from fgslam.errors import InputFileError
    from reloc.config import config_from_dict
    from sim.config import SimConfig
    from sim.tiled.presets import is_tiled, preset_config

    data: dict = {}
    if config is not None:
        if not config.is_file():
            raise InputFileError(f"{config}: simulator config file not found")
        try:
            data = yaml.safe_load(config.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputFileError(f"{config}: not valid YAML: {exc}") from exc
        if not isinstance(data, dict):
            raise InputFileError(f"{config}: the simulator config must be a mapping")
    base = preset_config(world, seed) if is_tiled(world) else None  # a kilometre preset's defaults
    cfg = config_from_dict(SimConfig, data, base=base)
    cfg = dataclasses.replace(cfg, world=world, seed=seed)
    if distance_m is not None:
        cfg = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse, distance_m=distance_m))
    return cfg


@app.command("sim")
def sim_cmd(
    world: str = typer.Option("my2021", "--world", help="World preset: a yard (my2020, my2021, my2022, cnes), a kilometre world (plains-2km, rocky-1km, cratered-3km, sparse-5km) or a Gazebo model directory."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random process of the run."),
    out: Path = typer.Option(..., "--out", help="Output directory (bag/, catalog.csv, rocks_true.csv, world.yaml, orbital.png)."),
    distance_m: float | None = typer.Option(None, "--distance-m", help="Traverse length in metres (default: the preset's)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the simulator config (see docs/sim.md)."),
    overwrite: bool = typer.Option(True, "--overwrite/--no-overwrite", help="Replace an existing bag in OUT."),
    detections: str = typer.Option(
        "statistical", "--detections",
        help="statistical (sensor models) | image (render + ONNX detectors, ~0.75 s per stereo frame).",
    ),
    image_rate_hz: float | None = typer.Option(
        None, "--image-rate-hz", help="Stereo frame rate of the image path (default: the stereo rate)."
    ),
) -> None:
    """Simulate a rover traverse and write a ROS 2 bag, the orbital catalog and the world files."""
    import time

    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from fgslam.io.sim_dir import write_sim_dir
    from sim.simulate import simulate
    from sim.tiled.presets import is_tiled

    if detections not in ("statistical", "image"):
        raise typer.BadParameter(f"--detections must be 'statistical' or 'image', got {detections!r}")
    console = Console(stderr=True)
    t0 = time.perf_counter()
    cfg = load_sim_config(world, seed, distance_m, config)
    if is_tiled(world):
        if detections != "statistical":
            raise typer.BadParameter("--detections image is for the yards; the kilometre worlds use the sensor models")
        _sim_tiled(cfg, out, overwrite, console)
        return
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                  console=console, transient=True) as progress:
        task = progress.add_task(f"simulating {world} (seed {seed})", total=2)
        run = simulate(cfg)
        if detections == "image":
            from sim.image_detections import ImageDetectionConfig, with_image_detections

            progress.update(task, description="rendering stereo/orbital images and detecting rocks")
            run = with_image_detections(run, ImageDetectionConfig(rate_hz=image_rate_hz))
        progress.update(task, advance=1, description="writing bag, catalog, world and orbital image")
        summary = write_sim_dir(run, out, overwrite=overwrite)
        progress.update(task, advance=1)
    wall = time.perf_counter() - t0
    s = run.stats
    rows = [
        ("distance", f"{s['distance_m']:.2f} m"),
        ("duration", f"{s['duration_s']:.1f} s"),
        *_sensor_rows(s),
        ("rocks / catalog entries", f"{s['n_rocks']} / {s['n_catalog']}"),
        ("catalog precision / recall", f"{s['catalog_precision']:.3f} / {s['catalog_recall']:.3f}"),
        ("bag", f"{summary.n_messages} messages, {summary.n_bytes / 1e6:.1f} MB"),
        ("wall time", f"{wall:.1f} s"),
    ]
    _print_table(f"fgslam sim: {run.world.name}, seed {seed}", rows)
    console.print(f"wrote {out}")


def _sensor_rows(s: dict) -> list[tuple[str, str]]:
    return [
        ("command dead-reckoning drift", f"{s['drift_pct']:.2f} %"),
        ("stereo precision / recall", f"{s['stereo_precision']:.3f} / {s['stereo_recall']:.3f}"),
        ("stereo frames / detections", f"{s['n_stereo_frames']} / {s['n_detections']}"),
    ]


def _print_table(title: str, rows: list[tuple[str, str]]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for row in rows:
        table.add_row(*row)
    Console().print(table)


def _sim_tiled(cfg, out: Path, overwrite: bool, console) -> None:
    """A kilometre-preset run: streamed to ``out`` with a progress bar, then a summary table."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from sim.tiled.outputs import simulate_to_bag

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f}"),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        tasks: dict = {}

        def report(stage: str, done: float, total: float) -> None:
            if stage not in tasks:
                label = {"drive": f"driving {cfg.world} (m)", "catalogs": "catalogs (tiles)", "image": "orbital image (tiles)"}
                tasks[stage] = progress.add_task(label.get(stage, stage), total=total)
            progress.update(tasks[stage], completed=done, total=total)

        run = simulate_to_bag(cfg, out, overwrite=overwrite, progress=report)
    s = run.stats
    rows = [
        ("world", f"{run.config.tiled.size_m / 1000:.2f} km square, rocks k {run.config.tiled.rocks.k:.0%}, "
                  f"surface {run.config.tiled.craters.age_gyr} Gyr"),
        ("distance / duration", f"{s['distance_m']:.1f} m / {s['duration_s']:.0f} s ({s['mean_speed_mps']:.3f} m/s)"),
        *_sensor_rows(s),
        ("rock catalog (precision)", f"{s['n_catalog']} ({s['catalog_precision']:.3f})"),
        ("craters: world / coverage / catalog", f"{s['n_craters_true']} / {s['n_craters_in_coverage']} / {s['n_craters_catalog']}"),
        ("bag", f"{s['bag_messages']} messages, {s['bag_bytes'] / 1e6:.1f} MB"),
        ("wall time (real-time factor)", f"{s['wall_total_s']:.1f} s ({s['real_time_factor']:.1f} x)"),
        ("CPU time (real-time factor)", f"{s['cpu_s']:.1f} s ({s['real_time_factor_cpu']:.1f} x)"),
        ("peak RSS", f"{s['peak_rss_mb']:.0f} MB"),
    ]
    _print_table(f"fgslam sim: {cfg.world}, seed {cfg.seed}", rows)
    console.print(f"wrote {out} (back-end calibration for this run: {out / 'backend.yaml'})")

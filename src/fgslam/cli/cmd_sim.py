"""``fgslam sim``: simulate a traverse in a Mars yard and write its bag, catalog and world files."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


def load_sim_config(world: str | None, seed: int | None, distance_m: float | None, config: Path | None):
    """The :class:`sim.SimConfig` from defaults, an optional YAML file (overrides or a saved
    world.yaml), then the command-line options (world and seed: the option, else the file's)."""
    import dataclasses

    from fgslam.config_file import read_yaml_mapping, sim_overrides
    from reloc.config import config_from_dict
    from reloc.errors import ConfigError
    from sim.config import SimConfig

    data = sim_overrides(read_yaml_mapping(config, "simulator config")) if config is not None else {}
    try:
        cfg = config_from_dict(SimConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{config}: {exc}") from None
    cfg = dataclasses.replace(cfg, world=cfg.world if world is None else world, seed=cfg.seed if seed is None else seed)
    if distance_m is not None:
        cfg = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse, distance_m=distance_m))
    return cfg


@app.command("sim")
def sim_cmd(
    world: str | None = typer.Option(None, "--world", help="World preset (my2020, my2021, my2022, cnes) or a Gazebo model directory [default: the --config file's, else my2021]."),
    seed: int | None = typer.Option(None, "--seed", help="Seed of every random process of the run [default: the --config file's, else 0]."),
    out: Path = typer.Option(..., "--out", help="Output directory (bag/, catalog.csv, rocks_true.csv, world.yaml, orbital.png)."),
    distance_m: float | None = typer.Option(None, "--distance-m", help="Traverse length in metres (default: the preset's)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the simulator config (see docs/sim.md)."),
    overwrite: bool = typer.Option(False, "--overwrite/--no-overwrite", help="Replace an earlier output in OUT (its bag, catalog and world files)."),
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
    from rich.table import Table

    from fgslam.io.sim_dir import sim_output_dir, write_sim_files
    from sim.simulate import simulate

    if detections not in ("statistical", "image"):
        raise typer.BadParameter(f"--detections must be 'statistical' or 'image', got {detections!r}")
    console = Console(stderr=True)
    t0 = time.perf_counter()
    cfg = load_sim_config(world, seed, distance_m, config)
    with sim_output_dir(out, overwrite) as od, \
            Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                     console=console, transient=True) as progress:
        task = progress.add_task(f"simulating {cfg.world} (seed {cfg.seed})", total=2)
        run = simulate(cfg)
        if detections == "image":
            from sim.image_detections import ImageDetectionConfig, with_image_detections

            progress.update(task, description="rendering stereo/orbital images and detecting rocks")
            run = with_image_detections(run, ImageDetectionConfig(rate_hz=image_rate_hz))
        progress.update(task, advance=1, description="writing bag, catalog, world and orbital image")
        summary = write_sim_files(run, od.staging)
        od.commit()
        progress.update(task, advance=1)
    wall = time.perf_counter() - t0
    s = run.stats
    table = Table(title=f"fgslam sim: {run.world.name}, seed {cfg.seed}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("distance", f"{s['distance_m']:.2f} m"),
        ("duration", f"{s['duration_s']:.1f} s"),
        ("command dead-reckoning drift", f"{s['drift_pct']:.2f} %"),
        ("stereo precision / recall", f"{s['stereo_precision']:.3f} / {s['stereo_recall']:.3f}"),
        ("stereo frames / detections", f"{s['n_stereo_frames']} / {s['n_detections']}"),
        ("rocks / catalog entries", f"{s['n_rocks']} / {s['n_catalog']}"),
        ("catalog precision / recall", f"{s['catalog_precision']:.3f} / {s['catalog_recall']:.3f}"),
        ("bag", f"{summary.n_messages} messages, {summary.n_bytes / 1e6:.1f} MB"),
        ("wall time", f"{wall:.1f} s"),
    ]
    for row in rows:
        table.add_row(*row)
    Console().print(table)
    console.print(f"wrote {out}")

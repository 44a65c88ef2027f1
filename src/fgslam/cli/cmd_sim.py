"""``fgslam sim``: simulate a traverse (a Mars yard or a kilometre world) and write its bag, catalogs and world files."""

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
    from sim.tiled.presets import is_tiled, preset_config

    data = sim_overrides(read_yaml_mapping(config, "simulator config")) if config is not None else {}
    name = world if world is not None else data.get("world", SimConfig.world)
    seed_ = seed if seed is not None else data.get("seed", SimConfig.seed)
    try:  # a kilometre preset's defaults first, the file's values over them
        base = preset_config(name, seed_) if isinstance(name, str) and is_tiled(name) else None
        cfg = config_from_dict(SimConfig, data, base=base)
    except ConfigError as exc:
        raise ConfigError(f"{config}: {exc}") from None
    cfg = dataclasses.replace(cfg, world=cfg.world if world is None else world, seed=cfg.seed if seed is None else seed)
    if distance_m is not None:
        cfg = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse, distance_m=distance_m))
    return cfg


@app.command("sim")
def sim_cmd(
    world: str | None = typer.Option(None, "--world", help="World preset: a yard (my2020, my2021, my2022, cnes), a kilometre world (plains-2km, rocky-1km, cratered-3km, sparse-5km) or a Gazebo model directory [default: the --config file's, else my2021]."),
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
    write_images: bool = typer.Option(
        False, "--write-images", help="With --detections image: write the rendered stereo pairs, their CameraInfo and the camera mounting (/tf_static) into the bag."
    ),
    bag_style: str = typer.Option(
        "fgslam", "--bag-style", help="fgslam (fgslam's topics, stamps from 0) | robot (/imu/data, /odom, an unstamped Twist on /cmd_vel, /stereo/*/image_raw/compressed, stamps from 2026-01-01; with --write-images no /rocks: the images are the rocks' input). Both write /tf, /tf_static and the catalog as markers (kilometre worlds: the catalog, made after the drive, is named in the bag's metadata)."
    ),
    epoch: str | None = typer.Option(
        None, "--epoch", help="First stamp: seconds since 1970 or an ISO date (2026-01-01T08:00:00Z) [default: the style's]."
    ),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
) -> None:
    """Simulate a rover traverse and write a ROS 2 bag, the orbital catalog and the world files."""
    import time

    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from fgslam.io.sim_dir import sim_output_dir, write_sim_files
    from sim.bag_scene import bag_style as named_style
    from sim.bag_scene import parse_epoch
    from sim.simulate import simulate
    from sim.tiled.presets import is_tiled

    if detections not in ("statistical", "image"):
        raise typer.BadParameter(f"--detections must be 'statistical' or 'image', got {detections!r}")
    if write_images and detections != "image":
        raise typer.BadParameter("--write-images needs --detections image (the images are rendered there)")
    style, topics = named_style(bag_style, parse_epoch(epoch))
    console = Console(stderr=True)
    t0 = time.perf_counter()
    cfg = load_sim_config(world, seed, distance_m, config)
    if is_tiled(cfg.world):
        if detections != "statistical":
            raise typer.BadParameter("--detections image is for the yards; the kilometre worlds use the sensor models")
        _sim_tiled(cfg, out, overwrite, console, force, style, topics)
        return
    with sim_output_dir(out, overwrite, force) as od, \
            Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                     console=console, transient=True) as progress:
        task = progress.add_task(f"simulating {cfg.world} (seed {cfg.seed})", total=2)
        run = simulate(cfg)
        frames: list = []
        image_cfg = None
        if detections == "image":
            from reloc.camera_bag import StereoFrame
            from sim.image_detections import ImageDetectionConfig, with_image_detections

            progress.update(task, description="rendering stereo/orbital images and detecting rocks")
            image_cfg = ImageDetectionConfig(rate_hz=image_rate_hz)
            keep = (lambda t, sr: frames.append(StereoFrame(t, sr.left, sr.right))) if write_images else None
            run = with_image_detections(run, image_cfg, on_frame=keep)
        progress.update(task, advance=1, description="writing bag, catalog, world and orbital image")
        summary = write_sim_files(run, od.staging, style, topics, frames or None,
                                  image_cfg.width_px if image_cfg else 640,
                                  rock_topic=not (write_images and bag_style == "robot"))
        od.commit()
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
    _print_table(f"fgslam sim: {run.world.name}, seed {cfg.seed}", rows)
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


def _sim_tiled(cfg, out: Path, overwrite: bool, console, force: bool = False, style=None, topics=None) -> None:
    """A kilometre-preset run: streamed into ``out``'s staging directory with a progress bar,
    committed whole (:mod:`fgslam.io.outdir`), then a summary table. ``style``/``topics``: the
    bag's (``--bag-style``, ``--epoch``)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from fgslam.io.sim_dir import sim_output_dir
    from sim.tiled.outputs import simulate_to_bag

    with sim_output_dir(out, overwrite, force) as od, Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f}"),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        tasks: dict = {}

        def report(stage: str, done: float, total: float) -> None:
            if stage not in tasks:
                label = {"drive": f"driving {cfg.world} (m)", "catalogs": "catalogs (tiles)", "image": "orbital image (tiles)",
                         "dem": "terrain model (blocks)"}
                tasks[stage] = progress.add_task(label.get(stage, stage), total=total)
            progress.update(tasks[stage], completed=done, total=total)

        run = simulate_to_bag(cfg, od.staging, overwrite=False, progress=report, style=style, topics=topics)
        od.commit()
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

"""``fgslam run``: one back-end over one traverse (a ``fgslam sim`` directory, or a bag + catalog)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import typer

from fgslam.cli.app import app
from fgslam.cli.viewer import CONNECT_HELP, SERVE_HELP, SPAWN_HELP

log = logging.getLogger(__name__)


def parse_floats(text: str, option: str, names: tuple[tuple[str, ...], ...]) -> tuple[float, ...]:
    """"a,b,c" -> finite floats, as many as one of the spellings in ``names``; errors name ``option``."""
    from fgslam.errors import InputFileError

    spellings = " or ".join(",".join(n) for n in names)
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputFileError(f"{option} must be {spellings}, got {text!r}") from None
    if len(values) not in {len(n) for n in names}:
        raise InputFileError(f"{option} must be {spellings} ({' or '.join(str(len(n)) for n in names)} numbers), got {text!r}")
    bad = [v for v in values if not math.isfinite(v)]
    if bad:
        raise InputFileError(f"{option} must hold finite numbers, got {text!r}")
    return values


def parse_start(start: str | None, sigma: str | None):
    """--start "X,Y,YAW" or "X,Y,Z,YAW" (m, rad) and --start-sigma "XY,YAW" or "XY,Z,YAW" (m, rad)
    -> :class:`fgslam.inputs.StartSpec`."""
    from fgslam.errors import InputFileError
    from fgslam.inputs import StartSpec

    spec = {}
    if start is not None:
        v = parse_floats(start, "--start", (("X", "Y", "YAW"), ("X", "Y", "Z", "YAW")))
        spec.update(xyyaw=(v[0], v[1], v[-1]), z_m=v[2] if len(v) == 4 else None)
    if sigma is not None:
        v = parse_floats(sigma, "--start-sigma", (("XY", "YAW"), ("XY", "Z", "YAW")))
        if min(v) <= 0:
            raise InputFileError(f"--start-sigma must hold 1-sigma values > 0 (m, rad), got {sigma!r}")
        spec.update(sigma_xy_m=v[0], sigma_yaw_rad=v[-1], sigma_z_m=v[1] if len(v) == 3 else None)
    return StartSpec(**spec)


def topic_map(config_topics: dict | None, options: list[str] | None) -> dict[str, str]:
    """The role -> topic map of a run: the config's ``topics:`` block, then ``--topic ROLE=NAME``
    options over it; checked (unknown roles, bad names) by :func:`fgslam.inputs.bag_topics`."""
    from fgslam.inputs import bag_topics
    from reloc.bag_spec import parse_topic_options

    merged = {**(config_topics or {}), **parse_topic_options(options or [])}
    bag_topics(merged)
    return merged


def load_inputs(directory: Path | None, bag: Path | None, catalog: Path | None, spec=None, topics=None,
                images=None, console=None):
    """The run inputs from DIR (``fgslam sim`` output) or from --bag/--catalog; ``spec``: the
    :class:`fgslam.inputs.StartSpec` of --start/--start-sigma; ``topics``: the bag's TopicNames;
    ``images``: the ImageInputConfig of a bag whose rocks come from its images (progress bar on
    ``console``)."""
    from contextlib import ExitStack

    from fgslam.errors import InputFileError
    from fgslam.inputs import load_bag, load_sim_dir

    if directory is not None and (bag is not None or catalog is not None):
        raise InputFileError("give either DIR or --bag/--catalog, not both")
    if directory is None and (bag is None or catalog is None):
        raise InputFileError("give a `fgslam sim` output DIR, or both --bag PATH and --catalog CSV")
    with ExitStack() as stack:
        progress = None
        if console is not None:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            bar = stack.enter_context(Progress(TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                                               TimeElapsedColumn(), console=console, transient=True))
            task = None

            def progress(done: int, total: int) -> None:
                nonlocal task
                if task is None:
                    task = bar.add_task("detecting rocks (images)", total=total)
                bar.update(task, completed=done)

        if directory is not None:
            return load_sim_dir(directory, spec, topics, images, progress)
        return load_bag(bag, catalog, spec, topics=topics, images=images, image_progress=progress)


def read_dem_option(path: Path | None):
    """The terrain model of ``--dem`` (None without one); a bad file is named with the option."""
    from fgslam.errors import InputFileError
    from fgslam.io.dem_tif import read_dem

    if path is None:
        return None
    try:
        return read_dem(path)
    except InputFileError as exc:
        raise InputFileError(f"--dem: {exc}") from None


def _unused_backend_yaml(directory: Path | None, config: Path | None) -> Path | None:
    """``directory``'s ``backend.yaml`` when it has one and no ``--config`` names another file."""
    f = None if config is not None or directory is None else Path(directory) / "backend.yaml"
    return f if f is not None and f.is_file() else None


def compare_dirs_config(directories: list[Path], config: Path | None) -> Path | None:
    """The one config a comparison of ``directories`` takes: ``--config`` when given; else the
    directories' ``backend.yaml`` when every one has the same (a kilometre world's: its sensors'
    calibration; compared without it rocky-1km's EKF ended at 0.99 m ATE and NEES 176 against
    0.40 m and 0.87 with it), else the defaults when none has one. Directories whose
    ``backend.yaml`` differ (or some without) cannot share one comparison config:
    :class:`~fgslam.errors.InputFileError` naming them, before any work."""
    from fgslam.config_file import read_yaml_mapping
    from fgslam.errors import InputFileError

    if config is not None:
        return config
    found = [_unused_backend_yaml(d, None) for d in directories]
    if all(f is None for f in found):
        return None
    mappings = [None if f is None else read_yaml_mapping(f, "backend.yaml") for f in found]
    if all(m == mappings[0] for m in mappings):
        log.info("using %s (the back-ends' calibration for these runs' sensors; --config FILE for another)", found[0])
        return found[0]
    groups: dict[str, list[str]] = {}
    for d, f, m in zip(directories, found, mappings):
        key = "no backend.yaml" if f is None else f"backend.yaml #{mappings.index(m) + 1}"
        groups.setdefault(key, []).append(str(d))
    listing = "; ".join(f"{k}: {', '.join(v)}" for k, v in groups.items())
    raise InputFileError(
        "the directories carry different back-end calibrations and one comparison shares one config "
        f"({listing}): compare them separately, or pass --config FILE for all")


def sim_dir_config(directory: Path | None, config: Path | None) -> Path | None:
    """The config a run of ``directory`` takes: ``--config`` when given, else the directory's
    ``backend.yaml`` when it has one (a kilometre world's: its sensors' calibration; without it
    rocky-1km with iSAM2 ended 4.1 m off in height after 1 km, 0.23 m with it), as ``./dev demo``
    does."""
    f = _unused_backend_yaml(directory, config)
    if f is None:
        return config
    log.info("using %s (the back-ends' calibration for this run's sensors; --config FILE for another)", f)
    return f


def load_config(path: Path | None):
    """CompareConfig from a YAML file of overrides or a saved config.yaml (defaults when None)."""
    from fgslam.config_file import load_compare_config

    return load_compare_config(path)


@app.command("run")
def run_cmd(
    directory: Path | None = typer.Argument(None, help="Output directory of `fgslam sim` (bag/, catalog.csv, ...)."),
    backend: str = typer.Option("isam2", "--backend", help="Back-end: ekf, isam2 (or dr, dead reckoning)."),
    no_reloc: bool = typer.Option(False, "--no-reloc", help="Run without relocalization fixes."),
    out: Path = typer.Option(..., "--out", help="Output directory."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Also write a rerun recording to this file."),
    bag: Path | None = typer.Option(None, "--bag", help="A ROS 2 bag (instead of DIR)."),
    catalog: Path | None = typer.Option(None, "--catalog", help="Orbital catalog CSV x,y,size,score (with --bag)."),
    dem: Path | None = typer.Option(None, "--dem", help="Orbital terrain model (GeoTIFF, world frame) whose heights the fixes carry; a DIR's dem.tif by default."),
    start: str | None = typer.Option(None, "--start", help="Start pose X,Y,YAW or X,Y,Z,YAW (m, rad) instead of the first ground truth; roll and pitch come from the IMU."),
    start_sigma: str | None = typer.Option(None, "--start-sigma", help="Start pose 1-sigma XY,YAW or XY,Z,YAW (m, rad) [default: 0.01 m, 0.002 rad]."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides (runner, relocalizer, backend_overrides, topics)."),
    topic: list[str] = typer.Option([], "--topic", help="Map an input role to a bag topic, ROLE=NAME (repeatable), e.g. --topic imu=/imu/data --topic wheel_odom=/odom."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
    spawn: bool = typer.Option(False, "--spawn", help=SPAWN_HELP),
    serve: int | None = typer.Option(None, "--serve", help=SERVE_HELP),
    connect: str | None = typer.Option(None, "--connect", help=CONNECT_HELP),
) -> None:
    """Run one back-end on a traverse; write <variant>.tum (e.g. isam2_reloc.tum), ground_truth.tum
    (with truth), metrics.json, fixes.csv, config.yaml."""
    from rich.console import Console

    from fgslam.api import run_one
    from fgslam.cli.progress import stream_progress
    from fgslam.cli.viewer import live_url
    from fgslam.inputs import bag_topics, with_dem
    from fgslam.io.outdir import OutputDir, atomic_path, check_output_path
    from fgslam.outputs import write_run_outputs

    console = Console(stderr=True)
    config = sim_dir_config(directory, config)
    cfg = load_config(config)
    topics = topic_map(cfg.topics, topic)
    spec = parse_start(start, start_sigma)
    live = live_url(spawn, serve, connect, console)
    terrain = read_dem_option(dem)  # before anything is written
    with OutputDir(out, "run", force=force) as od:  # checked, created and locked before any work
        rrd_staged = od.inside(rrd) if rrd is not None else None
        if rrd is not None and rrd_staged is None:
            check_output_path(rrd, "--rrd", directory=False)
        inputs = load_inputs(directory, bag, catalog, spec, bag_topics(topics), cfg.images, console)
        if terrain is not None:
            with_dem(inputs, terrain, dem)
        live_run = None
        if live is not None:  # pose by pose while the run goes (fgslam.viz.rerun_log.LiveRun)
            from fgslam.viz.rerun_log import LiveRun

            def live_run(key, gt):
                return LiveRun(live, inputs.name, key, inputs, gt)
        with stream_progress(inputs, console) as progress:
            outcome = run_one(inputs, backend, not no_reloc, cfg, topics, progress.callback, live=live_run)
        key, res, gt, met = outcome.key, outcome.result, outcome.gt, outcome.metrics
        write_run_outputs(od.staging, res, gt, met, outcome.used, key)
        if rrd is not None:  # in --out: part of the directory; elsewhere: its own atomic file
            from fgslam.viz.rerun_log import write_rrd

            items = [(inputs.name, inputs, gt, {key: res}, res.attempts)]
            if rrd_staged is not None:
                write_rrd(rrd_staged, items)
            else:
                with atomic_path(rrd, "--rrd") as tmp:
                    write_rrd(tmp, items)
        files = od.commit() + ([rrd] if rrd is not None and rrd_staged is None else [])
    if "ate" in met:
        console.print(f"{key}: ATE {met['ate']['rmse']:.3f} m, fixes {met['fixes']['fixes']} "
                      f"({met['fixes']['accepted']} accepted), wall {res.wall_s:.1f} s")
    for f in files:
        console.print(f"wrote {f}")

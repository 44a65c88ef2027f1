"""``fgslam run``: one back-end over one traverse (a ``fgslam sim`` directory, or a bag + catalog)."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from fgslam.cli.app import app


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


def load_inputs(directory: Path | None, bag: Path | None, catalog: Path | None, spec=None):
    """The run inputs from DIR (``fgslam sim`` output) or from --bag/--catalog; ``spec``: the
    :class:`fgslam.inputs.StartSpec` of --start/--start-sigma."""
    from fgslam.errors import InputFileError
    from fgslam.inputs import load_bag, load_sim_dir

    if directory is not None:
        if bag is not None or catalog is not None:
            raise InputFileError("give either DIR or --bag/--catalog, not both")
        return load_sim_dir(directory, spec)
    if bag is None or catalog is None:
        raise InputFileError("give a `fgslam sim` output DIR, or both --bag PATH and --catalog CSV")
    return load_bag(bag, catalog, spec)


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
    start: str | None = typer.Option(None, "--start", help="Start pose X,Y,YAW or X,Y,Z,YAW (m, rad) instead of the first ground truth; roll and pitch come from the IMU."),
    start_sigma: str | None = typer.Option(None, "--start-sigma", help="Start pose 1-sigma XY,YAW or XY,Z,YAW (m, rad) [default: 0.01 m, 0.002 rad]."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides (runner, relocalizer, backend_overrides)."),
) -> None:
    """Run one back-end on a traverse; write trajectory.tum, metrics.json, fixes.csv, config.yaml."""
    from rich.console import Console

    from fgslam.backends.registry import backend_config_dict, make_backend
    from fgslam.cli.progress import stream_progress
    from fgslam.compare import relocalizer_set, run_key, run_metrics
    from fgslam.fix_sources import NoFixes, OnlineFixes
    from fgslam.inputs import check_stream, truth_of
    from fgslam.io.outdir import OutputDir, atomic_path, check_output_path
    from fgslam.long_traverse import backend_overrides_for, stream_span_s
    from fgslam.outputs import write_run_outputs
    from fgslam.runner import run_backend
    from reloc.config import config_to_dict

    console = Console(stderr=True)
    cfg = load_config(config)
    spec = parse_start(start, start_sigma)
    with OutputDir(out, "run") as od:  # checked, created and locked before any work
        rrd_staged = od.inside(rrd) if rrd is not None else None
        if rrd is not None and rrd_staged is None:
            check_output_path(rrd, "--rrd", directory=False)
        inputs = load_inputs(directory, bag, catalog, spec)
        runner_cfg = check_stream(inputs, cfg.runner)
        gt = truth_of(inputs)
        span = gt.t[-1] - gt.t[0] if gt is not None and len(gt) else stream_span_s(inputs.measurements)
        be = make_backend(backend, inputs.initial,
                          backend_overrides_for(backend, cfg.backend_overrides.get(backend), span, cfg.long_traverse))
        relocs = [] if no_reloc else relocalizer_set(inputs, cfg)
        fixes = OnlineFixes(relocs) if relocs else NoFixes()
        key = run_key(backend, not no_reloc)
        with stream_progress(inputs, console) as progress:
            res = run_backend(be, inputs.measurements, fixes, config=runner_cfg, on_progress=progress.callback(key))
        met = run_metrics(res, gt, res.attempts, cfg.rpe_delta_m)
        used = {
            "backend": backend, "relocalization": not no_reloc, "inputs": inputs.source,
            "runner": config_to_dict(runner_cfg), "relocalizer": config_to_dict(cfg.relocalizer),
            "backend_config": backend_config_dict(be),
            "kind_relocalizers": {"+".join(r.kinds): config_to_dict(r.config) for r in relocs if r.kinds != ("rocks",)},
        }
        write_run_outputs(od.staging, res, gt, met, used)
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

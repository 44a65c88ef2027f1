"""``fgslam run``: one back-end over one traverse (a ``fgslam sim`` directory, or a bag + catalog)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


def parse_start(start: str | None) -> tuple[float, float, float] | None:
    """"X,Y,YAW" (m, m, rad) -> tuple, None when absent."""
    if start is None:
        return None
    from fgslam.errors import InputFileError

    try:
        x, y, yaw = (float(v) for v in start.split(","))
    except ValueError as exc:
        raise InputFileError(f"--start must be X,Y,YAW (metres, metres, radians), got {start!r}") from exc
    return x, y, yaw


def load_inputs(directory: Path | None, bag: Path | None, catalog: Path | None, start: str | None):
    """The run inputs from DIR (``fgslam sim`` output) or from --bag/--catalog."""
    from fgslam.errors import InputFileError
    from fgslam.inputs import load_bag, load_sim_dir

    start_xyyaw = parse_start(start)
    if directory is not None:
        if bag is not None or catalog is not None:
            raise InputFileError("give either DIR or --bag/--catalog, not both")
        return load_sim_dir(directory, start_xyyaw)
    if bag is None or catalog is None:
        raise InputFileError("give a `fgslam sim` output DIR, or both --bag PATH and --catalog CSV")
    return load_bag(bag, catalog, start_xyyaw)


def load_config(path: Path | None):
    """CompareConfig from a YAML file of overrides (defaults when None)."""
    from fgslam.compare import CompareConfig
    from fgslam.errors import InputFileError
    from reloc.config import config_from_dict

    if path is None:
        return CompareConfig()
    import yaml

    if not path.exists():
        raise InputFileError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputFileError(f"{path}: not valid YAML: {exc}") from exc
    return config_from_dict(CompareConfig, data, where="")


@app.command("run")
def run_cmd(
    directory: Path | None = typer.Argument(None, help="Output directory of `fgslam sim` (bag/, catalog.csv, ...)."),
    backend: str = typer.Option("isam2", "--backend", help="Back-end: ekf, isam2 (or dr, dead reckoning)."),
    no_reloc: bool = typer.Option(False, "--no-reloc", help="Run without relocalization fixes."),
    out: Path = typer.Option(..., "--out", help="Output directory."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Also write a rerun recording to this file."),
    bag: Path | None = typer.Option(None, "--bag", help="A ROS 2 bag (instead of DIR)."),
    catalog: Path | None = typer.Option(None, "--catalog", help="Orbital catalog CSV x,y,size,score (with --bag)."),
    start: str | None = typer.Option(None, "--start", help="Start pose X,Y,YAW (m, m, rad) when the bag has no ground truth."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides (runner, relocalizer, backend_overrides)."),
) -> None:
    """Run one back-end on a traverse; write trajectory.tum, metrics.json, fixes.csv, config.yaml."""
    from rich.console import Console

    from fgslam.backends.registry import backend_config_dict, make_backend
    from fgslam.cli.progress import stream_progress
    from fgslam.compare import relocalizer_set, run_key, run_metrics
    from fgslam.fix_sources import NoFixes, OnlineFixes
    from fgslam.inputs import truth_of
    from fgslam.outputs import write_run_outputs
    from fgslam.runner import run_backend
    from reloc.config import config_to_dict

    console = Console(stderr=True)
    cfg = load_config(config)
    inputs = load_inputs(directory, bag, catalog, start)
    gt = truth_of(inputs)
    be = make_backend(backend, inputs.initial, cfg.backend_overrides.get(backend))
    relocs = [] if no_reloc else relocalizer_set(inputs, cfg)
    fixes = OnlineFixes(relocs) if relocs else NoFixes()
    key = run_key(backend, not no_reloc)
    with stream_progress(inputs, console) as progress:
        res = run_backend(be, inputs.measurements, fixes, config=cfg.runner, on_progress=progress.callback(key))
    met = run_metrics(res, gt, res.attempts, cfg.rpe_delta_m)
    used = {
        "backend": backend, "relocalization": not no_reloc, "inputs": inputs.source,
        "runner": config_to_dict(cfg.runner), "relocalizer": config_to_dict(cfg.relocalizer),
        "backend_config": backend_config_dict(be),
        "kind_relocalizers": {"+".join(r.kinds): config_to_dict(r.config) for r in relocs if r.kinds != ("rocks",)},
    }
    files = write_run_outputs(out, res, gt, met, used)
    if rrd is not None:
        from fgslam.viz.rerun_log import write_rrd

        files.append(write_rrd(rrd, [(inputs.name, inputs, gt, {key: res}, res.attempts)]))
    if "ate" in met:
        console.print(f"{key}: ATE {met['ate']['rmse']:.3f} m, fixes {met['fixes']['fixes']} "
                      f"({met['fixes']['accepted']} accepted), wall {res.wall_s:.1f} s")
    for f in files:
        console.print(f"wrote {f}")

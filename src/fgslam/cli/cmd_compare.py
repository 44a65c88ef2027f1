"""``fgslam compare``: EKF and iSAM2, with and without relocalization, on the same inputs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from fgslam.cli.app import app
from fgslam.cli.viewer import CONNECT_HELP, SERVE_HELP, SPAWN_HELP


def compare_and_write(inputs_list: list, od, cfg, console, rrd: bool = True, live: str | None = None) -> list:
    """Compare every input (progress bars), write all outputs into the open
    :class:`~fgslam.io.outdir.OutputDir` ``od`` and commit it, print the table; returns the comparisons."""
    from fgslam.cli.progress import stream_progress
    from fgslam.compare import compare_world
    from fgslam.inputs import check_stream, stream_size
    from fgslam.outputs import write_comparison
    from fgslam.report import markdown_table

    comparisons = []
    for inputs in inputs_list:
        console.print(f"[bold]{inputs.name}[/bold]: {stream_size(inputs)}, "
                      + ", ".join(f"{len(c)} catalog {k}" for k, c in inputs.catalogs.items()))
        runner = check_stream(inputs, cfg.runner)
        run_cfg = cfg if runner == cfg.runner else dataclasses.replace(cfg, runner=runner)
        with stream_progress(inputs, console) as progress:
            comparisons.append(compare_world(inputs, run_cfg, on_progress=progress.update))
    write_comparison(od.staging, comparisons, cfg, rrd=rrd)
    if live is not None:  # the recording, streamed to the viewer too
        from fgslam.viz.rerun_log import stream_rrd

        stream_rrd(live, [(wc.inputs.name, wc.inputs, wc.gt, wc.runs, wc.attempts) for wc in comparisons])
    files = od.commit()
    print(markdown_table([wc.metrics for wc in comparisons]))
    for f in files:
        console.print(f"wrote {f}")
    return comparisons


def with_backends(cfg, backends: str | None):
    """``cfg`` with the --backends list (the reference back-end kept when listed, else the last)."""
    if not backends:
        return cfg
    from fgslam.errors import InputFileError
    from reloc.config import config_from_dict

    names = [b.strip() for b in backends.split(",") if b.strip()]
    if not names:
        raise InputFileError(f"--backends lists no back-end: {backends!r}")
    ref = cfg.reference_backend if cfg.reference_backend in names else names[-1]
    return config_from_dict(type(cfg), {"backends": names, "reference_backend": ref}, base=cfg)


@app.command("compare")
def compare_cmd(
    directories: list[Path] = typer.Argument(..., help="One or more `fgslam sim` output directories."),
    out: Path = typer.Option(..., "--out", help="Output directory (table.md, results.json, PNGs, compare.rrd)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the comparison config (default: the directories' backend.yaml when they carry one, the same for all)."),
    backends: str | None = typer.Option(None, "--backends", help="Comma-separated back-ends (default ekf,isam2)."),
    no_rrd: bool = typer.Option(False, "--no-rrd", help="Skip the rerun recording file."),
    spawn: bool = typer.Option(False, "--spawn", help=SPAWN_HELP),
    serve: int | None = typer.Option(None, "--serve", help=SERVE_HELP),
    connect: str | None = typer.Option(None, "--connect", help=CONNECT_HELP),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
) -> None:
    """Compare EKF and iSAM2 (each with and without the same relocalization fixes) on each DIR."""
    from rich.console import Console

    from fgslam.cli.cmd_run import compare_dirs_config, load_config
    from fgslam.cli.viewer import live_url
    from fgslam.inputs import bag_topics, load_sim_dir
    from fgslam.io.outdir import OutputDir

    console = Console(stderr=True)
    cfg = with_backends(load_config(compare_dirs_config(directories, config)), backends)
    live = live_url(spawn, serve, connect, console)
    with OutputDir(out, "compare", force=force) as od:  # checked, created and locked before any work
        topics = bag_topics(cfg.topics)
        inputs_list = [load_sim_dir(d, topics=topics) for d in directories]  # all inputs checked before any long work
        compare_and_write(inputs_list, od, cfg, console, rrd=not no_rrd, live=live)

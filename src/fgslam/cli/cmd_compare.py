"""``fgslam compare``: EKF and iSAM2, with and without relocalization, on the same inputs."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


def compare_and_write(inputs_list: list, out: Path, cfg, console, rrd: bool = True) -> list:
    """Compare every input (progress bars), write all outputs, print the table; returns the comparisons."""
    from fgslam.cli.progress import stream_progress
    from fgslam.compare import compare_world
    from fgslam.outputs import write_comparison
    from fgslam.report import markdown_table

    comparisons = []
    for inputs in inputs_list:
        console.print(f"[bold]{inputs.name}[/bold]: {len(inputs.measurements)} measurements, "
                      ", ".join(f"{len(c)} catalog {k}" for k, c in inputs.catalogs.items()))
        with stream_progress(inputs, console) as progress:
            comparisons.append(compare_world(inputs, cfg, on_progress=progress.update))
    files = write_comparison(out, comparisons, cfg, rrd=rrd)
    print(markdown_table([wc.metrics for wc in comparisons]))
    for f in files:
        console.print(f"wrote {f}")
    return comparisons


@app.command("compare")
def compare_cmd(
    directories: list[Path] = typer.Argument(..., help="One or more `fgslam sim` output directories."),
    out: Path = typer.Option(..., "--out", help="Output directory (table.md, results.json, PNGs, compare.rrd)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the comparison config."),
    backends: str | None = typer.Option(None, "--backends", help="Comma-separated back-ends (default ekf,isam2)."),
    no_rrd: bool = typer.Option(False, "--no-rrd", help="Skip the rerun recording."),
) -> None:
    """Compare EKF and iSAM2 (each with and without the same relocalization fixes) on each DIR."""
    import dataclasses

    from rich.console import Console

    from fgslam.cli.cmd_run import load_config
    from fgslam.inputs import load_sim_dir

    console = Console(stderr=True)
    cfg = load_config(config)
    if backends:
        names = tuple(b.strip() for b in backends.split(",") if b.strip())
        ref = cfg.reference_backend if cfg.reference_backend in names else names[-1]
        cfg = dataclasses.replace(cfg, backends=names, reference_backend=ref)
    inputs_list = [load_sim_dir(d) for d in directories]  # all inputs checked before any long work
    compare_and_write(inputs_list, out, cfg, console, rrd=not no_rrd)

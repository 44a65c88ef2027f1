"""``fgslam bench wrong-fixes``: a share of a traverse's fixes replaced by wrong ones, every back-end
(:mod:`fgslam.bench.wrong_fixes`)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("wrong-fixes")
def bench_wrong_fixes_cmd(
    directories: list[Path] = typer.Argument(..., help="fgslam sim directories."),
    fraction: float = typer.Option(0.2, "--fraction", help="Share of the fixes made wrong (seeded choice)."),
    offsets: str = typer.Option("5,50", "--offsets", help="LO,HI: a wrong fix is moved a distance uniform in [LO, HI] m."),
    backends: str = typer.Option("isam2,ekf", "--backends", help="Comma-separated back-ends; the first makes the fixes online."),
    seed: int = typer.Option(0, "--seed", help="Seed of the choice of wrong fixes and their offsets."),
    duration_s: float | None = typer.Option(None, "--duration-s", help="Run the first this many seconds of each bag (default: all)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides (default: each directory's backend.yaml)."),
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json and table.md."),
) -> None:
    """With good fixes and with a share of them wrong (5-50 m off, a good match's covariance): ATE,
    maximum error, its rise, and the wrong fixes each back-end accepted."""
    from rich.console import Console

    from fgslam.backends.registry import BACKEND_NAMES
    from fgslam.bench.wrong_fixes import WrongFixBenchConfig, bench_directory, summary_rows
    from fgslam.cli.bench_output import check_out, markdown_table, print_tables, write_results
    from fgslam.errors import InputFileError

    check_out(out)
    try:
        lo, hi = (float(v) for v in offsets.split(","))
    except ValueError:
        raise InputFileError(f"--offsets must be LO,HI in metres, got {offsets!r}") from None
    names = tuple(b.strip() for b in backends.split(",") if b.strip())
    bad = [b for b in names if b not in BACKEND_NAMES or b == "dead_reckoning"]
    if bad:
        raise InputFileError(f"--backends: unknown back-end(s) {bad}; choose from ekf, isam2")
    for d in directories:
        if not d.is_dir():
            raise InputFileError(f"{d}: not a directory (expected the output of `fgslam sim`)")
    cfg = WrongFixBenchConfig(fraction=fraction, offsets_m=(lo, hi), seed=seed, backends=names, duration_s=duration_s)
    err = Console(stderr=True)
    results = [bench_directory(d, cfg, config, progress=lambda s: err.print(s)) for d in directories]
    cols, rows = summary_rows(results)
    print_tables([(f"Wrong fixes: {fraction:.0%} of the fixes moved {lo:g}-{hi:g} m", cols, rows)], width=150)
    md = markdown_table(cols, rows)
    write_results(out, {"config": {"fraction": fraction, "offsets_m": [lo, hi], "backends": list(names), "seed": seed,
                                   "duration_s": duration_s, "config": str(config) if config else None},
                        "results": results}, md, err)

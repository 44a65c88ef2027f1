"""``fgslam bench craters``: crater relocalization and the ATE with and without craters on
``fgslam sim`` directories of the kilometre presets (:mod:`fgslam.bench.craters`)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("craters")
def bench_craters_cmd(
    directories: list[Path] = typer.Argument(..., help="fgslam sim directories (with craters.csv)."),
    backend: str = typer.Option("isam2", "--backend", help="Back-end of every pass: isam2 or ekf."),
    passes: str | None = typer.Option(None, "--passes", help="Comma-separated passes: no fixes, rocks alone, craters alone, rocks + craters."),
    wrong_fix_m: float = typer.Option(1.5, "--wrong-fix-m", help="A fix farther than this from the truth is wrong."),
    min_catalogued: int = typer.Option(6, "--min-catalogued", help="Catalogued craters mapped for an attempt to count."),
    duration_s: float | None = typer.Option(None, "--duration-s", help="Run the first this many seconds of each bag (default: all)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides, as `fgslam run --config` takes them (default: each directory's backend.yaml)."),
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json and table.md."),
) -> None:
    """Crater-only relocalization (success where enough catalogued craters are mapped, wrong fixes)
    and the ATE of rocks alone against rocks + craters, per directory."""
    from rich.console import Console

    from fgslam.bench.craters import PASSES, CraterBenchConfig, bench_directory, summary_rows
    from fgslam.cli.bench_output import check_out, markdown_table, print_tables, write_results
    from fgslam.errors import InputFileError

    check_out(out)
    names = tuple(p.strip() for p in passes.split(",")) if passes else tuple(PASSES)
    bad = [p for p in names if p not in PASSES]
    if bad:
        raise InputFileError(f"--passes: unknown pass(es) {bad}; choose from {list(PASSES)}")
    if backend not in ("isam2", "ekf"):
        raise InputFileError(f"--backend must be isam2 or ekf, got {backend!r}")
    if duration_s is not None and not duration_s > 0:
        raise InputFileError(f"--duration-s must be > 0, got {duration_s}")
    if not (wrong_fix_m > 0 and min_catalogued >= 3):
        raise InputFileError(f"--wrong-fix-m must be > 0 and --min-catalogued >= 3, got {wrong_fix_m}, {min_catalogued}")
    if config is not None:
        from fgslam.cli.cmd_run import load_config

        load_config(config)  # a bad file is named before any pass runs
    for d in directories:
        if not (d / "craters.csv").exists():
            raise InputFileError(f"{d}: no craters.csv (a kilometre-preset fgslam sim directory is needed)")
    err = Console(stderr=True)
    cfg = CraterBenchConfig(backend=backend, passes=names, wrong_fix_m=wrong_fix_m, min_catalogued=min_catalogued,
                            duration_s=duration_s)
    results = [bench_directory(d, cfg, progress=lambda s: err.print(s), config=config) for d in directories]
    cols, rows = summary_rows(results)
    print_tables([(f"Craters in the loop ({backend})", cols, rows)], width=170)
    md = markdown_table(cols, rows)
    write_results(out, {"config": {"backend": backend, "passes": list(names), "wrong_fix_m": wrong_fix_m,
                                   "min_catalogued": min_catalogued, "duration_s": duration_s,
                                   "config": str(config) if config else None}, "results": results}, md, err)

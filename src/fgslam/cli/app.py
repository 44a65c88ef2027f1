"""The typer applications that command modules register on (kept import-light)."""

from __future__ import annotations

import typer

app = typer.Typer(
    name="fgslam",
    help="Global localization for planetary rovers: simulate, match, run EKF / iSAM2, compare.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (speed and accuracy goals, reported as tables).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

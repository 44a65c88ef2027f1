"""The typer applications that command modules register on (kept import-light), and the options
every command shares: ``--version``, ``-v/--verbose`` (repeatable), ``-q/--quiet``."""

from __future__ import annotations

import logging

import typer

app = typer.Typer(
    name="fgslam",
    help="Global localization for planetary rovers: simulate, match, run EKF / iSAM2, compare.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (speed and accuracy goals, reported as tables).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
config_app = typer.Typer(help="Configuration files: the complete defaults, reusable with --config.", no_args_is_help=True)
app.add_typer(config_app, name="config")


def _print_version(value: bool) -> None:
    if value:
        from fgslam import __version__

        typer.echo(f"fgslam {__version__}")
        raise typer.Exit()


def log_level(verbose: int, quiet: bool) -> int:
    """The logging level of ``-v`` (INFO), ``-vv`` (DEBUG), ``-q`` (ERROR only); WARNING by default."""
    if quiet:
        return logging.ERROR
    return {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)


@app.callback()
def _common(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."),
    verbose: int = typer.Option(0, "-v", "--verbose", count=True, help="More log output (-v: info, -vv: debug)."),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="Log errors only."),
) -> None:
    """Global localization for planetary rovers: simulate, match, run EKF / iSAM2, compare."""
    if verbose and quiet:
        raise typer.BadParameter("-v and -q exclude each other")
    logging.getLogger().setLevel(log_level(verbose, quiet))

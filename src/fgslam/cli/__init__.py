"""``fgslam`` command line: one entry point, one module per command (``cmd_*.py``, discovered).

Command modules import heavy libraries inside their functions so that ``fgslam --help`` is fast.
Library errors (each package's exception base) become a one-line message and exit code 2.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import sys

from fgslam.cli.app import app, bench_app

__all__ = ["app", "bench_app", "main"]


def _register_commands() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name.startswith("cmd_"):
            importlib.import_module(f"{__name__}.{info.name}")


_register_commands()


def _error_types() -> tuple[type[BaseException], ...]:
    from ekf.errors import EkfError
    from fgslam.errors import FgslamError
    from reloc.errors import RelocError
    from sim.errors import SimError

    return (FgslamError, RelocError, EkfError, SimError, FileNotFoundError)


def main(argv: list[str] | None = None) -> int:
    """Console entry point: run the typer app, map library errors to exit code 2."""
    from fgslam.lifetime import Terminated, exit_watchdog, terminate_on_sigterm

    def _ending(code: int) -> None:  # the process's own entry point (not a caller's main([...])): it must end
        if argv is None:
            exit_watchdog(code)

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        with terminate_on_sigterm():  # SIGTERM unwinds like Ctrl-C: workers stopped, partial outputs removed
            result = app(args=argv, standalone_mode=False)
        if isinstance(result, int):  # click returns typer.Exit's code in non-standalone mode
            if result == 130:  # typer turns Ctrl-C into Exit(130)
                sys.stderr.write("fgslam: interrupted\n")
                _ending(130)
            return result
    except Terminated as exc:
        sys.stderr.write("fgslam: terminated\n")
        _ending(128 + exc.signum)
        return 128 + exc.signum
    except KeyboardInterrupt:
        sys.stderr.write("fgslam: interrupted\n")
        _ending(130)
        return 130
    except SystemExit as exc:  # typer/click exits for --help and usage errors
        return int(exc.code or 0)
    except _error_types() as exc:
        sys.stderr.write(f"fgslam: error: {exc}\n")
        return 2
    except Exception as exc:  # usage errors from click, or from the click that typer vendors
        names = {cls.__name__ for cls in type(exc).__mro__}
        if "ClickException" in names:
            exc.show()
            return int(exc.exit_code)
        if "Abort" in names:  # click's form of Ctrl-C
            sys.stderr.write("fgslam: interrupted\n")
            _ending(130)
            return 130
        raise
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""Output shared by the ``fgslam bench`` commands: progress ticks, rich tables, results files."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

Tick = Callable[[str, int], Callable[[], None]]


@contextlib.contextmanager
def progress_ticks(err: Console, label_width: int = 45) -> Iterator[Tick]:
    """Yield ``tick(name, total) -> advance()``: one progress bar per benchmark stage, on ``err``."""
    with Progress(TextColumn(f"{{task.description:<{label_width}}}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=err) as progress:
        def tick(name: str, total: int) -> Callable[[], None]:
            task = progress.add_task(name, total=total)
            return lambda: progress.advance(task)

        yield tick


def print_tables(tables: Iterable[tuple[str, Sequence[str], Sequence[Sequence[str]]]], width: int) -> None:
    """Print (title, columns, rows) tables on stdout, right-aligned, at least ``width`` wide."""
    from rich.markup import escape

    console = Console(width=max(Console().width, width))
    for title, cols, rows in tables:
        table = Table(title=escape(title))
        for c in cols:
            table.add_column(escape(c), justify="right")
        for r in rows:
            table.add_row(*(escape(str(v)) for v in r))  # units in brackets ("ATE [m]") are not markup
        console.print(table)


def check_out(out: Path | None) -> None:
    """Refuse an unusable --out before the benchmark runs (a file, not writable)."""
    if out is not None:
        from fgslam.io.outdir import check_output_path

        check_output_path(out, "--out")


def markdown_table(cols: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A (columns, rows) table as Markdown, for ``table.md``."""
    return ("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
            + "".join("| " + " | ".join(str(v) for v in r) + " |\n" for r in rows))


def write_results(out: Path | None, results: dict, markdown: str | None, err: Console, json_default=float) -> None:
    """Write ``out/results.json`` (and ``out/table.md`` when ``markdown`` is given) when ``out``
    is given, as a whole (:class:`fgslam.io.outdir.OutputDir`: staged, then committed)."""
    if out is None:
        return
    from fgslam.io.outdir import OutputDir

    with OutputDir(out, "bench") as od:
        (od.staging / "results.json").write_text(json.dumps(results, indent=2, default=json_default))
        if markdown is not None:
            (od.staging / "table.md").write_text(markdown)
        files = od.commit()
    err.print("wrote " + " and ".join(str(f) for f in files))

"""Rich progress bars over stream time, shared by the run/compare/demo commands."""

from __future__ import annotations

from contextlib import contextmanager


class StreamProgress:
    """One bar per stage, advancing with the stream time each stage has reached."""

    def __init__(self, progress, t0: float, t1: float) -> None:
        self.progress = progress
        self.t0, self.t1 = t0, t1
        self.tasks: dict[str, int] = {}

    def update(self, stage: str, t: float) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=max(self.t1 - self.t0, 1e-9))
        self.progress.update(self.tasks[stage], completed=min(t - self.t0, self.t1 - self.t0))

    def callback(self, stage: str):
        return lambda t: self.update(stage, t)


@contextmanager
def stream_progress(inputs, console):
    """Context manager yielding a :class:`StreamProgress` for ``inputs``' time span."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from fgslam.inputs import stream_span_s

    t0, t1 = stream_span_s(inputs)
    with Progress(TextColumn("{task.description:<28}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TimeElapsedColumn(), console=console, transient=False) as progress:
        yield StreamProgress(progress, t0, t1)

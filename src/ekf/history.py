"""Bounded state history for late fixes: periodic state checkpoints plus the input log since
the oldest one, so that the filter can roll back to any time in the window and replay."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from ekf.state import FilterState


@dataclass(frozen=True)
class Entry:
    """One processed input: ``kind`` "step" | "obs" | "fix", its time (step end, frame time,
    fix t_meas) and the input itself."""

    kind: str
    t: float
    item: Any


@dataclass(frozen=True)
class Checkpoint:
    """A snapshot of the state taken after ``log_index`` entries of the log (never mutated)."""

    t: float
    log_index: int
    state: FilterState
    n_trajectory: int


class History:
    """Checkpoints (oldest first) and the log of entries since the oldest checkpoint."""

    def __init__(self, history_s: float) -> None:
        self.history_s = history_s
        self.log: list[Entry] = []
        self.checkpoints: list[Checkpoint] = []

    @property
    def t_start(self) -> float:
        """Oldest time a fix can be rolled back to."""
        return self.checkpoints[0].t if self.checkpoints else float("inf")

    def checkpoint(self, state: FilterState, n_trajectory: int) -> None:
        """Snapshot ``state`` at the current end of the log."""
        self.checkpoints.append(Checkpoint(state.t, len(self.log), state.copy(), n_trajectory))

    def prune(self, t_now: float) -> None:
        """Forget checkpoints (and log entries) that are not needed to reach ``t_now - history_s``."""
        horizon = t_now - self.history_s
        drop = 0
        while drop + 1 < len(self.checkpoints) and self.checkpoints[drop + 1].t <= horizon:
            drop += 1
        if drop:
            del self.checkpoints[:drop]
            cut = self.checkpoints[0].log_index
            del self.log[:cut]
            self.checkpoints = [replace(c, log_index=c.log_index - cut) for c in self.checkpoints]

    def latest_before(self, t: float) -> int:
        """Index of the newest checkpoint taken at or before ``t`` (-1 if none)."""
        for i in range(len(self.checkpoints) - 1, -1, -1):
            if self.checkpoints[i].t <= t:
                return i
        return -1

    def rewind(self, i: int) -> list[Entry]:
        """Drop checkpoints after ``i`` and return (and remove) the log entries after it."""
        c = self.checkpoints[i]
        tail = self.log[c.log_index :]
        del self.log[c.log_index :]
        del self.checkpoints[i + 1 :]
        return tail

    def snapshot(self) -> tuple[list[Entry], list[Checkpoint]]:
        """Shallow copies of the log and checkpoint list (checkpoint states are never mutated)."""
        return list(self.log), list(self.checkpoints)

    def restore(self, snap: tuple[list[Entry], list[Checkpoint]]) -> None:
        """Undo everything since :meth:`snapshot`."""
        self.log, self.checkpoints = list(snap[0]), list(snap[1])

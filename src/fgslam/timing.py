"""Timing as a wrapper: a back-end whose calls that change its state are timed (wall, and CPU on
request).

:class:`TimedBackend` forwards the :class:`reloc.backend.Backend` protocol; ``predict``,
``observe``, ``apply_fix``, ``expect_fix`` and ``trajectory`` add their wall time to ``busy_s``
and, with ``cpu=True``, their CPU time to ``busy_cpu_s`` (a process-CPU clock read costs ~1 us,
ten times a wall-clock read: benchmarks ask for it, runs do not); the queries (``estimate``, ``landmark_map``, ``stats``) are
not counted (an online relocalizer's map snapshot counts as matching time, see
:class:`fgslam.fix_sources.OnlineFixes`).
"""

from __future__ import annotations

import time

from reloc.backend import Backend

_clock, _cpu = time.perf_counter, time.process_time


def _no_cpu() -> float:
    return 0.0


class TimedBackend:
    """``backend`` with its busy time measured (see module doc)."""

    def __init__(self, backend: Backend, cpu: bool = False) -> None:
        self.inner = backend
        self.name = backend.name
        self.config = backend.config
        self.busy_s = 0.0
        self.busy_cpu_s = 0.0
        self._cpu = _cpu if cpu else _no_cpu

    def _timed(self, fn, *args):
        w, c = _clock(), self._cpu()
        out = fn(*args)
        self.busy_s += _clock() - w
        self.busy_cpu_s += self._cpu() - c
        return out

    def predict(self, step):
        return self._timed(self.inner.predict, step)

    def observe(self, obs):
        return self._timed(self.inner.observe, obs)

    def apply_fix(self, fix):
        return self._timed(self.inner.apply_fix, fix)

    def expect_fix(self, t_meas: float):
        return self._timed(self.inner.expect_fix, t_meas)

    def trajectory(self):
        return self._timed(self.inner.trajectory)

    def estimate(self):
        return self.inner.estimate()

    def landmark_map(self, kind: str):
        return self.inner.landmark_map(kind)

    def stats(self):
        return self.inner.stats()

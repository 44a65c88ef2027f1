"""Timing as a wrapper: a back-end whose calls that change its state are timed (wall, and CPU on
request).

:class:`TimedBackend` forwards the :class:`reloc.backend.Backend` protocol; ``predict``,
``observe``, ``apply_fix``, ``expect_fix`` and ``trajectory`` add their wall time to ``busy_s``
(each ``observe``, one landmark frame's update, also to ``frame_latency``, and its CPU time on
the calling thread to ``frame_cpu_latency``: the update's cost, whatever else the machine runs;
the passes limit BLAS to one thread, so the thread's clock holds all of it)
and, with ``cpu=True``, their CPU time to ``busy_cpu_s`` (a process-CPU clock read costs ~1 us,
ten times a wall-clock read: benchmarks ask for it, runs do not); the queries (``estimate``, ``landmark_map``, ``stats``) are
not counted (an online relocalizer's map snapshot counts as matching time, see
:class:`fgslam.fix_sources.OnlineFixes`).
"""

from __future__ import annotations

import time

import numpy as np

from reloc.backend import Backend

_clock, _cpu, _thread_cpu = time.perf_counter, time.process_time, time.thread_time


def _no_cpu() -> float:
    return 0.0


class LatencyHistogram:
    """Wall times of many calls in log-spaced bins (1 us to 100 s, 20 bins a decade): percentiles
    within 12 % at a memory that does not grow with the run."""

    EDGES_S = np.logspace(-6, 2, 161)

    def __init__(self) -> None:
        self.counts = np.zeros(self.EDGES_S.size + 1, dtype=np.int64)
        self.n = 0
        self.max_s = 0.0

    def add(self, dt_s: float) -> None:
        self.counts[int(np.searchsorted(self.EDGES_S, dt_s))] += 1
        self.n += 1
        self.max_s = max(self.max_s, dt_s)

    def percentile_s(self, q: float) -> float:
        """The ``q`` percentile (0-100) in seconds: the upper edge of its bin (nan when empty)."""
        if self.n == 0:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.counts), np.ceil(q / 100.0 * self.n)))
        return float(min(self.EDGES_S[min(k, self.EDGES_S.size - 1)], self.max_s))

    def to_dict(self) -> dict:
        """n, median, p99 and max in ms."""
        return {"n": self.n, "median_ms": 1e3 * self.percentile_s(50), "p99_ms": 1e3 * self.percentile_s(99),
                "max_ms": 1e3 * self.max_s}


class TimedBackend:
    """``backend`` with its busy time measured (see module doc)."""

    def __init__(self, backend: Backend, cpu: bool = False) -> None:
        self.inner = backend
        self.name = backend.name
        self.config = backend.config
        self.busy_s = 0.0
        self.busy_cpu_s = 0.0
        self._cpu = _cpu if cpu else _no_cpu
        self.frame_latency = LatencyHistogram()  # each landmark frame's update (observe)
        self.frame_cpu_latency = LatencyHistogram()  # the same, CPU time of the calling thread

    def _timed(self, fn, *args):
        w, c = _clock(), self._cpu()
        out = fn(*args)
        self.busy_s += _clock() - w
        self.busy_cpu_s += self._cpu() - c
        return out

    def predict(self, step):
        return self._timed(self.inner.predict, step)

    def observe(self, obs):
        w, c = _clock(), _thread_cpu()
        out = self._timed(self.inner.observe, obs)
        self.frame_cpu_latency.add(_thread_cpu() - c)
        self.frame_latency.add(_clock() - w)
        return out

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

"""The timing wrapper: a frame's update is timed on the wall clock and on its thread's CPU clock,
so a pass on a loaded machine still reports what the update costs."""

from __future__ import annotations

import time

from fgslam.timing import TimedBackend


class _Sleeper:
    """A back-end whose frame update waits (as if the machine were busy elsewhere) or computes."""

    name = "sleeper"
    config = None

    def __init__(self, busy: bool) -> None:
        self.busy = busy

    def observe(self, obs) -> None:
        if self.busy:
            sum(i * i for i in range(200_000))  # a fixed amount of work
        else:
            time.sleep(0.02)


def test_a_waiting_update_costs_wall_time_and_no_cpu():
    sleeper = TimedBackend(_Sleeper(False))
    for _ in range(5):
        sleeper.observe(None)
    wall, cpu = sleeper.frame_latency.to_dict(), sleeper.frame_cpu_latency.to_dict()
    assert wall["n"] == cpu["n"] == 5 and wall["median_ms"] >= 19.0 and cpu["p99_ms"] < 5.0


def test_a_computing_update_costs_its_cpu_time():
    worker = _Sleeper(True)
    c0 = time.thread_time()
    worker.observe(None)
    cost_ms = 1e3 * (time.thread_time() - c0)
    be = TimedBackend(worker)
    for _ in range(5):
        be.observe(None)
    wall, cpu = be.frame_latency.to_dict(), be.frame_cpu_latency.to_dict()
    assert 0.5 * cost_ms <= cpu["median_ms"] <= 2.0 * cost_ms
    assert wall["max_ms"] >= 0.85 * cpu["max_ms"]  # (log bins: within 12 %)

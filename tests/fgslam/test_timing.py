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
        t_end = time.perf_counter() + 0.02
        if self.busy:
            while time.perf_counter() < t_end:
                pass
        else:
            time.sleep(0.02)


def test_a_waiting_update_costs_wall_time_and_no_cpu():
    for busy in (False, True):
        be = TimedBackend(_Sleeper(busy))
        for _ in range(5):
            be.observe(None)
        wall, cpu = be.frame_latency.to_dict(), be.frame_cpu_latency.to_dict()
        assert wall["n"] == cpu["n"] == 5 and wall["median_ms"] >= 19.0
        if busy:
            assert cpu["median_ms"] >= 15.0
        else:
            assert cpu["p99_ms"] < 5.0

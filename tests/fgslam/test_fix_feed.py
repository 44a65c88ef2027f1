"""The streamed fix list a replay consumes while the reference pass is still running."""

from __future__ import annotations

import queue

import numpy as np
import pytest

from fgslam.passes import FixFeedError, QueueFixFeed
from reloc.measurements import GlobalFix


def _fix(t_meas: float, delay: float = 2.0) -> GlobalFix:
    return GlobalFix(t_meas, t_meas + delay, t_meas, 0.0, 0.0, np.eye(3) * 0.01)


def test_feed_returns_a_fix_only_once_the_reference_is_past_its_receive_time():
    q: queue.Queue = queue.Queue()
    feed = QueueFixFeed(q, timeout_s=0.2)
    q.put(("fix", _fix(3.0)))  # t_recv 5
    q.put(("time", 5.0))  # fixes with t_recv < 5 known: not enough to answer "up to 5"
    with pytest.raises(FixFeedError, match="sent nothing"):
        feed.until(5.0)
    q.put(("fix", _fix(4.0)))  # t_recv 6
    q.put(("time", 6.5))
    assert [f.t_meas for f in feed.until(5.0)] == [3.0]
    assert feed.until(5.5) == []
    assert [f.t_meas for f in feed.until(6.0)] == [4.0]
    q.put(("fix", _fix(7.0)))
    q.put(("done", None))
    assert [f.t_meas for f in feed.until(100.0)] == [7.0]
    assert feed.rest() == []


def test_feed_reports_a_failed_reference_pass():
    q: queue.Queue = queue.Queue()
    q.put(("error", "SmootherError: indeterminant system"))
    with pytest.raises(FixFeedError, match="indeterminant"):
        QueueFixFeed(q, timeout_s=1.0).until(1.0)


def test_passes_without_fixes_are_started_costliest_first():
    """Longest processing time first: the smoother's pass before the EKF's before dead reckoning,
    equal costs in their given order (the order only schedules, results do not depend on it)."""
    from fgslam.backends.registry import backend_class
    from fgslam.passes import Pass, by_cost

    ps = [Pass("dr", "dr", None, "none", "dr"), Pass("ekf", "ekf", None, "none", "ekf"),
          Pass("isam2", "isam2", None, "none", "isam2"), Pass("ekf2", "ekf", None, "none", "ekf2")]
    assert [p.key for p in by_cost(ps)] == ["isam2", "ekf", "ekf2", "dr"]
    costs = [backend_class(n).relative_cost for n in ("isam2", "ekf", "dr")]
    assert costs == sorted(costs, reverse=True) and costs[1] == 1.0

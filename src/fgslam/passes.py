"""Scheduling of a comparison's back-end passes, sequentially or on forked worker processes.

Sequentially: the reference pass (online relocalization; it produces the shared fix list) and
the passes without relocalization, then the replays of the fix list. On workers, the replays do
not wait for the reference pass to finish: they start beside it and receive its fixes as they are
produced, over a queue (:class:`QueueFixFeed`), together with how far its stream has got; a
replay only waits when it catches up with the reference. It receives exactly the list it would
have been given at the end, so the worker count never changes a result, only the wall time.
Workers are forked (Linux): the inputs are inherited, not pickled; progress travels back over a
queue. The reference pass is submitted first, so it is always running while a replay waits.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue as queue_mod
import threading
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass

import numpy as np

from fgslam.backends.registry import backend_class, make_backend
from fgslam.errors import FgslamError
from fgslam.fix_sources import FedFixes, FixProducer, FixSource, NoFixes, OnlineFixes, ReplayedFixes
from fgslam.lifetime import kill_pool, signals_deferred, worker_initializer
from fgslam.runner import RunnerConfig, RunResult, run_backend, shared_steps

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Pass:
    """One back-end pass: ``mode`` is "none" (no fixes), "online" (own relocalizer) or "replay"."""

    key: str
    backend: str
    overrides: dict | None
    mode: str
    label: str


_STATE: dict = {}  # set in the parent before forking (under _FORK_LOCK); read by the workers
_FORK_LOCK = threading.Lock()  # one forked comparison at a time per process (threads may share it)
FEED_TIMEOUT_S = 900.0  # a replay gives up when the reference pass is silent this long


class FixFeedError(FgslamError):
    """The reference pass failed or went silent, so a replay cannot get its fixes."""


class QueueFixFeed:
    """Consumer side of a reference pass's fixes (see :class:`fgslam.fix_sources.FixFeed`). Messages:
    ("fix", GlobalFix), ("time", t): every fix with ``t_recv < t`` has been sent, ("done", None),
    ("error", text)."""

    def __init__(self, q, timeout_s: float = FEED_TIMEOUT_S) -> None:
        self._q, self._timeout_s = q, timeout_s
        self._buf: list = []
        self._horizon = -float("inf")
        self._done = False

    def _pull(self) -> None:
        try:
            kind, payload = self._q.get(timeout=self._timeout_s)
        except queue_mod.Empty:
            raise FixFeedError(f"the reference pass sent nothing for {self._timeout_s:.0f} s") from None
        if kind == "fix":
            self._buf.append(payload)
        elif kind == "time":
            self._horizon = max(self._horizon, float(payload))
        elif kind == "done":
            self._done = True
        else:
            raise FixFeedError(f"the reference pass failed: {payload}")

    def until(self, t: float) -> list:
        """Fixes with ``t_recv <= t`` not returned yet, in production order."""
        while not self._done and self._horizon <= t:
            self._pull()
        out = [f for f in self._buf if f.t_recv <= t]
        self._buf = [f for f in self._buf if f.t_recv > t]
        return out

    def rest(self) -> list:
        """Every fix not returned yet (after the reference pass has finished)."""
        while not self._done:
            self._pull()
        out, self._buf = self._buf, []
        return out


def _source(state: dict, p: Pass, fixes, fix_feed, fix_sink) -> FixSource:
    """The pass's fixes: its own relocalizers (online), the reference's list or feed (replay)."""
    if p.mode == "online":
        return OnlineFixes(state["relocalizers"], fix_sink)
    if p.mode == "replay":
        return FedFixes(fix_feed) if fix_feed is not None else ReplayedFixes(fixes)
    return NoFixes()


def _execute(state: dict, p: Pass, fixes, on_progress, fix_feed=None, fix_sink=None) -> RunResult:
    inputs = state["inputs"]
    be = make_backend(p.backend, inputs.initial, p.overrides)
    steps = state.get("steps")
    res = run_backend(be, inputs.measurements, _source(state, p, fixes, fix_feed, fix_sink),
                      config=state["runner"], on_progress=on_progress, keep_truth=False,  # the caller has it
                      steps=steps)
    if steps is not None:
        res.extra["shared_front_end_s"] = steps.seconds  # spent once, before the passes, not in their wall_s
    return res


def _worker(p: Pass, fixes) -> tuple[str, RunResult]:
    q = _STATE.get("queue")
    cb = (lambda t: q.put((p.label, t))) if q is not None else None
    feeds = _STATE.get("feeds", {})
    if p.mode == "replay" and fixes is None:
        return p.key, _execute(_STATE, p, None, cb, fix_feed=QueueFixFeed(feeds[p.key]))
    if p.mode == "online" and feeds:
        def sink(kind: str, payload) -> None:
            for fq in feeds.values():
                fq.put((kind, payload))

        try:
            res = _execute(_STATE, p, None, cb, fix_sink=sink)
        except BaseException as exc:
            sink("error", f"{type(exc).__name__}: {exc}")
            raise
        sink("done", None)
        return p.key, res
    return p.key, _execute(_STATE, p, fixes, cb)


def by_cost(passes: list[Pass]) -> list[Pass]:
    """``passes`` costliest first by their back-end's ``relative_cost`` (stable among equals)."""
    return sorted(passes, key=lambda p: -float(getattr(backend_class(p.backend), "relative_cost", 1.0)))


def run_passes(
    inputs, passes: list[Pass], runner_cfg: RunnerConfig, relocalizers: list[FixProducer],
    fixes_of: Callable[[RunResult], list], workers: int | None = 1,
    on_progress: Callable[[str, float], None] | None = None,
) -> dict[str, RunResult]:
    """Run ``passes`` (exactly one "online", with ``relocalizers``); replays get
    ``fixes_of(online result)``. ``workers``: 1 in this process, one after the other; N on N
    forked processes (and one per replay); None every pass at once on its own forked process."""
    online = [p for p in passes if p.mode == "online"]
    if len(online) != 1:
        raise ValueError(f"exactly one online (reference) pass is needed, got {len(online)}")
    wave1 = online + [p for p in passes if p.mode == "none"]
    wave2 = [p for p in passes if p.mode == "replay"]
    for p in passes:  # import every back-end before forking: workers share the parent's code
        backend_class(p.backend)
    state = {"inputs": inputs, "runner": runner_cfg, "relocalizers": list(relocalizers)}
    if isinstance(inputs.measurements, list) and len(passes) > 1:  # every pass's front-end, once
        state["steps"] = shared_steps(inputs.measurements, runner_cfg)
        log.info("front-end of %d measurements computed once for %d passes in %.1f s",
                 len(inputs.measurements), len(passes), state["steps"].seconds)
    if (workers is not None and workers <= 1) or "fork" not in mp.get_all_start_methods():
        results: dict[str, RunResult] = {}
        for p in wave1:
            results[p.key] = _execute(state, p, None, (lambda t, lab=p.label: on_progress(lab, t)) if on_progress else None)
        fixes = fixes_of(results[online[0].key])
        for p in wave2:
            results[p.key] = _execute(state, p, fixes, (lambda t, lab=p.label: on_progress(lab, t)) if on_progress else None)
        return results
    with _FORK_LOCK:
        _STATE.clear()
        _STATE.update(state)
        try:
            return _run_forked(online, wave1, wave2, fixes_of, workers, on_progress)
        finally:
            _STATE.clear()


def _run_forked(online, wave1, wave2, fixes_of, workers, on_progress) -> dict[str, RunResult]:
    results: dict[str, RunResult] = {}
    ctx = mp.get_context("fork")
    q = ctx.Queue() if on_progress else None
    _STATE["queue"] = q
    _STATE["feeds"] = {p.key: ctx.Queue() for p in wave2}
    # a replay spends much of its time waiting for the reference's fixes: it gets a process of its
    # own on top of the ``workers`` computing ones, so a waiting replay never holds a core's turn
    # the workers die with this process whatever ends it (fgslam.lifetime): killed or
    # interrupted, a comparison leaves no orphan blocked on its queue
    spare = frozenset(mp.active_children())  # children that are not this pool's
    size = len(wave1) + len(wave2) if workers is None else workers + len(wave2)
    pool = ProcessPoolExecutor(max_workers=size, mp_context=ctx,
                               initializer=worker_initializer, initargs=(os.getpid(),))
    try:
        # FIFO: the reference pass starts first, the replays next (they stream its fixes), then
        # the passes without relocalization, the costliest first (longest processing time
        # first: a long pass started last would run alone at the end); the first submit forks
        # every worker
        order = online + wave2 + by_cost([p for p in wave1 if p.mode == "none"])
        with signals_deferred():
            futures: dict[Future, Pass] = {pool.submit(_worker, p, None): p for p in order}
        while futures:
            done, _ = wait(list(futures), timeout=0.2, return_when=FIRST_COMPLETED)
            _drain(q, on_progress)
            for fut in done:
                p = futures.pop(fut)
                key, res = fut.result()
                results[key] = res
                if on_progress:
                    on_progress(p.label, res.t_end)
        _drain(q, on_progress)
    except BaseException:  # a failed pass, Ctrl-C, SIGTERM (fgslam.lifetime.Terminated): stop them all now
        kill_pool(pool, spare)
        raise
    pool.shutdown(wait=True)
    ref = results[online[0].key]
    expected = fixes_of(ref)
    for p in wave2:  # the streamed list must be the reference's list, fix for fix
        got = results[p.key].fixes_sent
        want = [f for f in expected if f.t_recv <= results[p.key].t_end]
        if len(got) != len(want) or not all(map(_same_fix, got, want)):
            raise FixFeedError(f"replay {p.key!r} received {len(got)} fixes, the reference produced {len(want)}")
    return results


def _same_fix(a, b) -> bool:
    return (a.t_meas, a.t_recv, a.x_m, a.y_m, a.yaw_rad) == (b.t_meas, b.t_recv, b.x_m, b.y_m, b.yaw_rad) \
        and bool(np.array_equal(a.cov_xyyaw, b.cov_xyyaw))


def _drain(q, on_progress) -> None:
    if q is None or on_progress is None:
        return
    while True:
        try:
            label, t = q.get_nowait()
        except queue_mod.Empty:
            return
        on_progress(label, t)

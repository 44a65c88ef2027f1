"""Scheduling of a comparison's back-end passes, sequentially or on forked worker processes.

Wave 1: the reference pass (online relocalization; it produces the shared fix list), dead
reckoning, and every pass without relocalization. Wave 2: the replays of the fix list, submitted
as soon as the reference pass is done. Passes are deterministic, so the worker count never
changes a result, only the wall time. Workers are forked (Linux): the inputs are inherited, not
pickled; progress travels back over a queue.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue as queue_mod
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass

from fgslam.backends.registry import backend_class, make_backend
from fgslam.relocalizer import Relocalizer
from fgslam.runner import RunnerConfig, RunResult, run_backend

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Pass:
    """One back-end pass: ``mode`` is "none" (no fixes), "online" (own relocalizer) or "replay"."""

    key: str
    backend: str
    overrides: dict | None
    mode: str
    label: str


_STATE: dict = {}  # set in the parent before forking; read by the workers


def _execute(p: Pass, fixes, on_progress) -> RunResult:
    inputs, runner_cfg, reloc = _STATE["inputs"], _STATE["runner"], _STATE["relocalizer"]
    be = make_backend(p.backend, inputs.initial, p.overrides)
    return run_backend(
        be, inputs.measurements,
        relocalizer=reloc if p.mode == "online" else None,
        fixes=fixes if p.mode == "replay" else None,
        config=runner_cfg, on_progress=on_progress,
    )


def _worker(p: Pass, fixes) -> tuple[str, RunResult]:
    q = _STATE.get("queue")
    cb = (lambda t: q.put((p.label, t))) if q is not None else None
    return p.key, _execute(p, fixes, cb)


def run_passes(
    inputs, passes: list[Pass], runner_cfg: RunnerConfig, relocalizer: Relocalizer,
    fixes_of: Callable[[RunResult], list], workers: int = 1,
    on_progress: Callable[[str, float], None] | None = None,
) -> dict[str, RunResult]:
    """Run ``passes`` (exactly one "online"); replays get ``fixes_of(online result)``."""
    online = [p for p in passes if p.mode == "online"]
    if len(online) != 1:
        raise ValueError(f"exactly one online (reference) pass is needed, got {len(online)}")
    wave1 = online + [p for p in passes if p.mode == "none"]
    wave2 = [p for p in passes if p.mode == "replay"]
    for p in passes:  # import every back-end before forking: workers share the parent's code
        backend_class(p.backend)
    _STATE.update(inputs=inputs, runner=runner_cfg, relocalizer=relocalizer, queue=None)
    results: dict[str, RunResult] = {}
    if workers <= 1 or "fork" not in mp.get_all_start_methods():
        for p in wave1:
            results[p.key] = _execute(p, None, (lambda t, lab=p.label: on_progress(lab, t)) if on_progress else None)
        fixes = fixes_of(results[online[0].key])
        for p in wave2:
            results[p.key] = _execute(p, fixes, (lambda t, lab=p.label: on_progress(lab, t)) if on_progress else None)
        return results
    ctx = mp.get_context("fork")
    q = ctx.Queue() if on_progress else None
    _STATE["queue"] = q
    try:
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futures: dict[Future, Pass] = {pool.submit(_worker, p, None): p for p in wave1}
            pending_replays = list(wave2)
            while futures:
                done, _ = wait(list(futures), timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(q, on_progress)
                for fut in done:
                    p = futures.pop(fut)
                    key, res = fut.result()
                    results[key] = res
                    if on_progress:
                        on_progress(p.label, res.t_end)
                    if p.mode == "online":
                        fixes = fixes_of(res)
                        for r in pending_replays:
                            futures[pool.submit(_worker, r, fixes)] = r
                        pending_replays = []
            _drain(q, on_progress)
    finally:
        _STATE.clear()
    return results


def _drain(q, on_progress) -> None:
    if q is None or on_progress is None:
        return
    while True:
        try:
            label, t = q.get_nowait()
        except queue_mod.Empty:
            return
        on_progress(label, t)

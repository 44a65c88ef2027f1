"""Running a campaign on Dask: an existing cluster (its scheduler address) or a local one.

Each task is one ``fgslam.campaign.task.run_task`` call on a worker (small dict in, small dict
out). Records are appended to ``OUT/results.jsonl`` as they complete (``as_completed``), so an
interrupted campaign resumes where it stopped: tasks whose latest record succeeded with the same
overrides are skipped; failed tasks run again. A task that fails, on the worker or in the
cluster (a worker lost), is recorded with its error text and the campaign goes on.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from fgslam.campaign.results import ResultStore, identity, latest
from fgslam.campaign.spec import CampaignError, CampaignSpec, expand
from fgslam.campaign.task import run_task
from fgslam.io.outdir import write_text_atomic

log = logging.getLogger(__name__)

TASK_FUNCTION = run_task  # what the workers run (importable: fgslam.campaign.task.run_task)


def require_dask():
    """The ``dask.distributed`` module, or a :class:`CampaignError` naming the extra to install."""
    try:
        import dask.distributed as dd
    except ImportError as exc:
        raise CampaignError(
            "campaigns run on Dask, which is not installed: pip install 'fgslam[dask]' "
            f"(dask + distributed) ({exc})"
        ) from exc
    return dd


@contextmanager
def dask_client(scheduler: str | None = None, n_workers: int = 2) -> Iterator:
    """A ``dask.distributed.Client`` on ``scheduler`` (address) or on a new local cluster of
    ``n_workers`` single-threaded worker processes bound to 127.0.0.1; closed on exit."""
    dd = require_dask()
    if scheduler:
        try:
            client = dd.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise CampaignError(f"cannot connect to the Dask scheduler at {scheduler!r}: {exc}") from exc
        with client:
            yield client
        return
    if n_workers < 1:
        raise CampaignError(f"--workers must be >= 1, got {n_workers}")
    # dashboard_address=None turns the dashboard off, but the scheduler's small HTTP server (health,
    # metrics) would still bind 8787: a random local port lets several campaigns share a machine.
    with dd.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster, \
            dd.Client(cluster) as client:
        yield client


@dataclass
class CampaignRun:
    """What one invocation did: the records of the spec's tasks (latest each, in task order),
    how many tasks it computed and skipped, and its wall time (s)."""

    records: list[dict]
    computed: int
    skipped: int
    wall_s: float
    n_workers: int


def cluster_error_record(task: dict, exc: BaseException) -> dict:
    """Record of a task the cluster could not run (worker lost, function not importable there)."""
    return {**{k: task[k] for k in ("key", "world", "variant", "seed", "config_hash", "overrides")},
            "status": "error", "error": f"{type(exc).__name__}: {exc}", "traceback": "", "runtime": {}}


def run_campaign(
    spec: CampaignSpec,
    out_dir: Path,
    *,
    scheduler: str | None = None,
    n_workers: int = 2,
    on_start: Callable[[int, int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
    task_function: Callable[[dict], dict] | None = None,
) -> CampaignRun:
    """Run every task of ``spec`` not already done in ``out_dir`` on Dask; returns all its records.

    ``on_start(to_run, skipped)`` is called once the cluster is up, ``on_result(record)`` after each
    record is written. ``task_function`` (default :func:`~fgslam.campaign.task.run_task`) must be
    importable on the workers.
    """
    t0 = time.perf_counter()
    tasks = expand(spec)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "campaign.json", json.dumps(spec.to_dict(), indent=2, sort_keys=True, default=str))
    store = ResultStore(out_dir)
    done = store.done()
    todo = [t for t in tasks if identity(t) not in done]
    skipped = len(tasks) - len(todo)
    if skipped:
        log.info("resuming: %d of %d tasks already done in %s", skipped, len(tasks), store.path)
    fn = task_function or TASK_FUNCTION
    workers = n_workers
    if todo:
        with dask_client(scheduler, n_workers) as client:
            dd = require_dask()
            workers = len(client.nthreads()) or n_workers
            if on_start:
                on_start(len(todo), skipped)
            stamp = time.time_ns()  # keys unique per invocation: a shared cluster may still hold old ones
            futures = {client.submit(fn, t, pure=False, key=f"fgslam-campaign-{stamp}-{i}"): t
                       for i, t in enumerate(todo)}
            for fut in dd.as_completed(list(futures)):
                task = futures.pop(fut)
                try:
                    if fut.status == "cancelled":
                        raise RuntimeError("task cancelled (a worker or the scheduler was lost?)")
                    record = fut.result()  # re-raises what the task function raised
                except Exception as exc:  # noqa: BLE001 -- recorded; the campaign goes on
                    log.warning("task %s failed in the cluster: %s", task["key"], exc)
                    record = cluster_error_record(task, exc)
                store.append(record)
                fut.release()
                if on_result:
                    on_result(record)
    elif on_start:
        on_start(0, skipped)
    by_id = latest(store.records())
    records = [by_id[identity(t)] for t in tasks if identity(t) in by_id]
    return CampaignRun(records, len(todo), skipped, time.perf_counter() - t0, workers)

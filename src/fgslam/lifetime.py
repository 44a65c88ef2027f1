"""Worker processes that die with their parent, however the parent ends (SIGINT, SIGTERM, SIGKILL).

A forked worker blocked on its queue outlives a killed parent: orphaned, holding its memory
(the whole inherited traverse) for ever. :func:`die_with_parent`, called first thing in the
worker, asks the kernel to kill it when the parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``; the
signal comes when the *thread* that forked it ends, which for a process pool is the thread that
runs the pool, alive until the pool is shut down), or, where that is not available, starts a
thread that watches the parent's pid. :func:`terminate_on_sigterm` turns SIGTERM into an
exception in the main process, so that its cleanup (stopping workers, removing a half-written
output) runs as it does for Ctrl-C.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

from fgslam.errors import FgslamError

log = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
WATCH_PERIOD_S = 0.5


class Terminated(BaseException):
    """SIGTERM reached the process (a BaseException, like KeyboardInterrupt: nothing swallows it)."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(f"terminated by signal {signum}")
        self.signum = signum


def _pdeathsig() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(WATCH_PERIOD_S)


def die_with_parent(parent_pid: int) -> None:
    """Make this (child) process die as soon as ``parent_pid``, its parent, does."""
    armed = _pdeathsig()
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch, args=(parent_pid,), name="parent-watch", daemon=True).start()


def worker_initializer(parent_pid: int) -> None:
    """Process-pool initializer: die with the parent; leave Ctrl-C to it (the terminal sends SIGINT
    to the whole group; the parent then stops its workers itself, without a traceback from each)."""
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the parent's handler (nor a deferred one)


EXIT_GRACE_S = 10.0


def exit_watchdog(code: int, grace_s: float = EXIT_GRACE_S) -> None:
    """After a signal: make sure this process ends with ``code`` within ``grace_s`` s. Its cleanup
    (outputs removed, workers killed) has run; what remains is the interpreter's own shutdown,
    which waits for every non-daemon thread and child process it knows of, and a worker or thread
    left in an odd state by the signal can make that wait for ever. Live children are killed."""
    for p in mp.active_children():
        with contextlib.suppress(Exception):
            p.kill()

    def _force() -> None:
        time.sleep(grace_s)
        log.warning("shutdown did not finish within %.0f s of the signal: exiting", grace_s)
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os._exit(code)

    threading.Thread(target=_force, name="exit-watchdog", daemon=True).start()


def kill_pool(pool, spare: frozenset = frozenset()) -> None:
    """Stop a ``ProcessPoolExecutor`` now: its workers are killed, pending work cancelled (the
    pool's own shutdown would wait for every running task to finish).

    A signal that lands while the pool forks its workers can leave one started but not yet in the
    pool's table; multiprocessing would then wait for it at exit for ever. Every live child of
    this process not in ``spare`` (those that were alive before the pool) is killed with the pool's.
    """
    procs = getattr(pool, "_processes", None)  # private, but the only handle on the workers
    procs = set(procs.values()) if isinstance(procs, dict) else set()
    procs |= set(mp.active_children()) - set(spare)
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it
    for p in procs:
        with contextlib.suppress(Exception):
            p.kill()
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(timeout=5.0)
    # the pool's manager thread closes its wake-up pipe as it ends; the interpreter's exit hook
    # writes to that pipe without the pool's lock, and a close racing that write printed
    # "Exception ignored ... Bad file descriptor" at exit. Waiting for the thread here leaves the
    # pipe closed (and marked so) before any exit hook runs.
    if manager is not None and manager is not threading.current_thread():
        manager.join(timeout=5.0)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while the block forks workers; one that came is acted on (the
    handler it would have met is called) when the block ends.

    Raised while a pool forks, the exception from a signal lands in the middle of its bookkeeping
    (a worker started but not yet recorded, then waited for at exit for ever) or inside an at-fork
    hook, where Python prints and drops it (the run then goes on as if never signalled). Blocking
    the signals in this thread would not do: any other thread (a progress bar's) still takes them.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum, frame):
        held.append(signum)

    previous = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if held:
            s = held[0]
            if callable(previous[s]):
                previous[s](s, None)
            elif previous[s] == signal.SIG_DFL:
                signal.raise_signal(s)


@contextlib.contextmanager
def terminate_on_sigterm() -> Iterator[None]:
    """Within the block (main thread only), SIGTERM raises :class:`Terminated`."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class ForkedTaskError(FgslamError):
    """A task run on a forked process failed, or its process died."""


class Forked:
    """``fn()`` run now on a forked child process (inherited, not pickled: any closure will do)
    that dies with this one (:func:`die_with_parent`) and ignores Ctrl-C (the parent's to handle);
    :meth:`result` waits for its return value (pickled back: keep it small) and raises
    :class:`ForkedTaskError` naming ``what`` if it raised or its process died. Linux only (fork)."""

    def __init__(self, fn, what: str) -> None:
        self.what = what
        ctx = mp.get_context("fork")
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_forked_main, args=(fn, send, os.getpid()), name=what, daemon=True)
        self._proc.start()
        send.close()

    def result(self):
        try:
            kind, payload = self._recv.recv()
        except EOFError:
            self._proc.join()
            raise ForkedTaskError(f"{self.what}: its process died (exit code {self._proc.exitcode})") from None
        finally:
            self._recv.close()
        self._proc.join()
        if kind == "error":
            raise ForkedTaskError(f"{self.what} failed: {payload}")
        return payload

    def kill(self) -> None:
        """Stop the child now (the parent gave up on its result)."""
        with contextlib.suppress(Exception):
            self._proc.kill()
            self._proc.join()
            self._recv.close()


def _forked_main(fn, send, parent_pid: int) -> None:
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        out = ("ok", fn())
    except BaseException as exc:  # noqa: BLE001 (everything goes back to the parent, named)
        out = ("error", f"{type(exc).__name__}: {exc}")
    try:
        send.send(out)
    finally:
        send.close()

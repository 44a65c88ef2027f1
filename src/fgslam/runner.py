"""Runner: feed a time-ordered measurement stream to one back-end, with relocalization.

The loop is the algorithm: for each measurement, *deliver the fixes that are due*, then
*predict* (motion inputs, assembled into odometry steps and corrected for wheel slip and a gyro
bias by the front-end, :mod:`fgslam.front_end`) or *observe* (a landmark frame of any registered
kind, :mod:`reloc.kinds`, which the front-end sees too); ground-truth poses
are only collected for evaluation. Beside it: where fixes come from (one
:class:`fgslam.fix_sources.FixSource`: online relocalizers, a replayed list, a feed), the
recording of the online estimate at ``record_rate_hz`` (:class:`RunRecorder`), and the wall time
of the back-end's calls (:class:`fgslam.timing.TimedBackend`), and an optional
:class:`RunObserver` (a live viewer) told of each recorded estimate and each fix outcome as they
happen.

The stream is consumed lazily, one measurement at a time (any iterable: a list, a generator
over a bag being read). The run records the online estimate (with covariance), the final
``trajectory()``, every attempt and fix outcome, the landmark maps by kind, and timings.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import gc
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from ekf.blas import blas_limit
from fgslam.errors import FgslamError
from fgslam.fix_hold import FixHoldConfig, hold_far_fixes, settle
from fgslam.fix_sources import FixSource, NoFixes
from fgslam.front_end import MOTION_INPUTS, FrontEnd, SharedSteps
from fgslam.relocalizer import FixAttempt
from fgslam.timing import TimedBackend
from reloc.backend import Backend, BackendStats, FixOutcome, LandmarkMap, PoseEstimate, Trajectory
from reloc.config import NonNegative, NonNegativeInt, Positive, checked
from reloc.gyro import GyroConfig
from reloc.kinds import UnknownKindError, kind_of
from reloc.measurements import GlobalFix, GroundTruthPose
from reloc.rows import RowBuffer
from reloc.slip import SlipConfig

log = logging.getLogger(__name__)

PROGRESS_EVERY = 300  # odometry steps between progress reports


class RunnerError(FgslamError):
    """The stream cannot be run (empty, no IMU, a measurement of no known type)."""


@dataclass(frozen=True)
@checked(RunnerError)
class RunnerConfig:
    """Recording rate and odometry source (defaults in code)."""

    record_rate_hz: Positive = 10.0
    speed_source: Literal["cmd", "wheel"] = "cmd"  # see OdometryAssembler
    max_imu_gap_s: Positive = 1.0
    # a speed input older than this no longer moves the rover (a base stops without commands):
    # a gap in /cmd_vel or /wheel_odom, or in the IMU with the limit above raised, is not driven
    # through at the last speed
    max_speed_age_s: Positive = 1.0
    # BLAS threads during the pass (0: library default). The back-ends and the matcher do small
    # dense algebra (<= ~1000 x 1000) one call at a time: a threaded BLAS makes it slower, and a
    # comparison already runs one pass per core (measured on my2020, iSAM2 over 150 s of stream:
    # 16.0 s of back-end time with OpenBLAS's default threads, 8.2 s with one).
    blas_threads: NonNegativeInt = 1
    # the objects alive when the pass starts (the stream read into memory, the catalogs, the
    # back-end's set-up) are kept out of the garbage collector's full passes while it runs
    # (gc.freeze, undone at the end): each full pass walked all of them, 156-204 ms in one frame
    # on the demo's 430 000 objects (first 700 s, iSAM2), now ~23 000
    freeze_heap: bool = True
    rss_every_m: Positive = 500.0  # resident memory sampled every this many metres of estimated path
    # the allocator's free memory handed back to the OS every this many seconds of stream time
    # (glibc's malloc_trim; 0: never; nothing where the C library has none). GTSAM and numpy free
    # and allocate blocks of every size at every update, and glibc keeps what they free: over
    # plains-2km (iSAM2 + reloc) the resident memory grew 496 -> 598 MB from 0.25 to 1.75 km while
    # what a trim left stayed at 398-466 MB up to ~1.5 km (docs/app.md, "whole traverses and their memory")
    trim_heap_every_s: NonNegative = 120.0
    # wheel slip seen by the landmarks corrects the odometry of both back-ends (reloc.slip): the
    # fault table's 60 s stuck rover (docs/sim.md)
    slip: SlipConfig = field(default_factory=SlipConfig)
    # a gyro bias step seen by the landmarks corrects the IMU's heading for both back-ends
    # (reloc.gyro): the fault table's IMU bias step (docs/sim.md)
    gyro: GyroConfig = field(default_factory=GyroConfig)
    # a fix far from the estimate waits for a second one that agrees (fgslam.fix_hold): wrong
    # fixes that a drifted back-end's own gates would take
    fix_hold: FixHoldConfig = field(default_factory=FixHoldConfig)


@dataclass
class RunResult:
    """Everything one back-end pass produced (see module doc). Times in stream seconds;
    ``landmarks`` maps each observed kind's name to its final map."""

    backend: str
    online: Trajectory  # estimate as it was at the time, at record_rate_hz, with covariance
    final: Trajectory  # backend.trajectory() after the last input
    ground_truth: Trajectory | None
    attempts: list[FixAttempt]
    outcomes: list[FixOutcome]
    fixes_sent: list[GlobalFix]
    landmarks: dict[str, LandmarkMap]
    stats: BackendStats
    wall_s: float
    backend_s: float
    match_s: float
    t_start: float
    t_end: float
    cpu_s: float = 0.0  # process CPU time of the pass
    backend_cpu_s: float = 0.0  # CPU time inside the back-end's calls (with time_cpu)
    extra: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start

    @property
    def n_landmarks(self) -> int:
        return sum(len(m) for m in self.landmarks.values())


def ground_truth_trajectory(poses: Iterable[GroundTruthPose]) -> Trajectory | None:
    """Stack ground-truth messages (any iterable, consumed once) into a Trajectory (None when
    there are none)."""
    rows = RowBuffer(8)
    for g in poses:
        rows.append((g.t, *g.position_m, *g.quat_xyzw))
    return truth_from_rows(rows)


def truth_from_rows(rows: RowBuffer) -> Trajectory | None:
    """Rows t, position, quaternion xyzw -> a Trajectory (None when there are none), built block
    by block: a 24-hour traverse's 30 Hz truth is 2.6 M poses, and the rows' copy and a rotation
    matrix per row at once would add ~360 MB to the 340 MB of the trajectory itself."""
    if not len(rows):
        return None
    t, T = np.empty(len(rows)), np.empty((len(rows), 4, 4))
    T[:] = np.eye(4)
    k = 0
    for block in rows.blocks():
        n = len(block)
        t[k:k + n] = block[:, 0]
        T[k:k + n, :3, :3] = Rotation.from_quat(block[:, 4:8]).as_matrix()
        T[k:k + n, :3, 3] = block[:, 1:4]
        k += n
    return Trajectory(t, T, None)


class RunObserver(Protocol):
    """Told of the run as it goes (e.g. :class:`fgslam.viz.rerun_log.LiveRun`): every recorded
    online estimate (``record_rate_hz``) and every fix outcome, when they happen."""

    def recorded(self, est: PoseEstimate) -> None: ...

    def fix(self, outcome: FixOutcome) -> None: ...


class RunRecorder:
    """The online estimate every ``1 / rate_hz`` s of stream time (after an odometry step), the
    ground truth, the stream's span, and progress reports."""

    def __init__(self, rate_hz: float, on_progress: Callable[[float], None] | None, rss_every_m: float = 500.0,
                 observer: RunObserver | None = None, keep_truth: bool = True) -> None:
        self.dt = 1.0 / rate_hz
        self.keep_truth = keep_truth
        self.on_progress = on_progress
        self.observer = observer
        self.t_first = self.t_last = None
        self.next_record = None
        self.records = RowBuffer(1 + 16 + 36)  # t, T_world_base, cov
        self.truth = RowBuffer(1 + 3 + 4)  # t, position, quaternion xyzw
        self.n_predict = 0
        self.rss_every_m = rss_every_m
        self.distance_m = 0.0  # along the recorded online estimate
        self.memory: list[dict] = []  # resident memory every rss_every_m metres (and at the end)

    def saw(self, t: float) -> None:
        if self.t_first is None:
            self.t_first = self.next_record = t
        self.t_last = t

    def saw_truth(self, g: GroundTruthPose) -> None:
        if self.keep_truth:
            self.truth.append((g.t, *g.position_m, *g.quat_xyzw))

    def predicted(self, t: float, backend: Backend) -> None:
        self.n_predict += 1
        if t >= self.next_record:
            est = backend.estimate()
            if len(self.records):
                d0 = self.distance_m
                last_T = self.records.last()[1:17].reshape(4, 4)
                self.distance_m += float(np.linalg.norm(est.position_m[:2] - last_T[:2, 3]))
                if int(self.distance_m // self.rss_every_m) > int(d0 // self.rss_every_m):
                    self.sample_memory(t)
            self.records.append(np.concatenate(([est.t], np.ravel(est.T_world_base), np.ravel(est.cov))))
            if self.observer is not None:
                self.observer.recorded(est)
            self.next_record = self.t_first + self.dt * (np.floor((t - self.t_first) / self.dt + 1e-9) + 1)

    def sample_memory(self, t: float) -> None:
        """Record the process's resident and peak resident memory (MB) at ``t``."""
        self.memory.append({"distance_m": round(self.distance_m, 1), "t": float(t), **resident_memory_mb()})

    def progress(self, t: float) -> None:
        if self.on_progress is not None and self.n_predict % PROGRESS_EVERY == 0:
            self.on_progress(t)

    def online(self) -> Trajectory:
        r = self.records.array()
        return Trajectory(r[:, 0].copy(), r[:, 1:17].reshape(-1, 4, 4), r[:, 17:].reshape(-1, 6, 6))

    def ground_truth(self) -> Trajectory | None:
        return truth_from_rows(self.truth)


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim`` (None where the C library has none: musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        fn = getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None
    if fn is not None:
        fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def release_free_heap() -> bool:
    """Hand the allocator's free memory back to the OS (``malloc_trim(0)``); whether any was."""
    fn = _malloc_trim()
    return bool(fn(0)) if fn is not None else False


class HeapTrim:
    """:func:`release_free_heap` every ``every_s`` of stream time (0: never); counts the trims
    and their CPU time."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.next_t: float | None = None
        self.n = 0
        self.cpu_s = 0.0

    def tick(self, t: float) -> None:
        if self.every_s <= 0:
            return
        if self.next_t is None:
            self.next_t = t + self.every_s
        elif t >= self.next_t:
            self.next_t = t + self.every_s
            c0 = time.process_time()
            release_free_heap()
            self.cpu_s += time.process_time() - c0
            self.n += 1

    def stats(self) -> dict:
        return {"n": self.n, "cpu_s": round(self.cpu_s, 3)}


def resident_memory_mb() -> dict:
    """The process's resident memory now and at its peak (MB; Linux /proc, else the peak only)."""
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    try:
        with open("/proc/self/statm") as f:
            now = int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        now = float("nan")
    return {"rss_mb": round(now, 1), "peak_rss_mb": round(peak, 1)}


def _landmark_kind(m, t: float) -> str:
    try:
        return kind_of(m).name
    except UnknownKindError as exc:
        raise RunnerError(f"the runner cannot consume {type(m).__name__} at t={t}: {exc}") from None


def run_backend(
    backend: Backend,
    measurements: Iterable,
    fixes: FixSource | None = None,
    *,
    config: RunnerConfig | None = None,
    on_progress: Callable[[float], None] | None = None,
    time_cpu: bool = False,
    observer: RunObserver | None = None,
    keep_truth: bool = True,
    steps: SharedSteps | None = None,
) -> RunResult:
    """Run ``backend`` over ``measurements`` (time-ordered, consumed lazily) with fixes from
    ``fixes`` (:mod:`fgslam.fix_sources`; default none); ``time_cpu`` also measures the CPU time
    of the back-end's calls (``RunResult.backend_cpu_s``, benchmarks); ``observer`` is told of
    each recorded estimate and fix outcome as the run goes (a live viewer). ``keep_truth=False``:
    the caller holds the ground truth already (``RunResult.ground_truth`` is then None; a
    24-hour traverse's 30 Hz truth is ~170 MB of rows, and a forked pass would send it back).
    ``steps``: the front-end of these very ``measurements`` under this config, computed once for
    several passes (:class:`fgslam.front_end.SharedSteps`; ignored if it is another's)."""
    cfg = config or RunnerConfig()
    front = steps.for_pass() if steps is not None and steps.matches(measurements, cfg) else FrontEnd(cfg)
    with blas_limit(cfg.blas_threads), frozen_heap(cfg.freeze_heap):
        be = TimedBackend(hold_far_fixes(backend, cfg.fix_hold), cpu=time_cpu)
        return _run(be, measurements, fixes or NoFixes(), cfg, front, on_progress, observer, keep_truth)


_FREEZE_LOCK = threading.Lock()
_freeze = {"depth": 0, "ours": False}  # passes inside frozen_heap (threads may run several); did we freeze


@contextlib.contextmanager
def frozen_heap(enabled: bool = True):
    """While inside: the objects alive on entry (after a collection) are frozen (``gc.freeze``),
    so the collector's full passes walk only what the run creates; the first to enter freezes,
    the last to leave unfreezes (a frozen cycle that becomes garbage is collected afterwards). A
    process that froze objects itself keeps its own freeze: nothing is done then."""
    if not enabled:
        yield
        return
    with _FREEZE_LOCK:
        if _freeze["depth"] == 0 and gc.get_freeze_count() == 0:
            gc.collect()
            gc.freeze()
            _freeze["ours"] = True
        _freeze["depth"] += 1
    try:
        yield
    finally:
        with _FREEZE_LOCK:
            _freeze["depth"] -= 1
            if _freeze["depth"] == 0 and _freeze["ours"]:
                gc.unfreeze()
                _freeze["ours"] = False


def shared_steps(measurements: list, config: RunnerConfig | None = None) -> SharedSteps:
    """The front-end of an in-memory stream, once for all the passes run on it (see :func:`run_backend`)."""
    return SharedSteps(measurements, config or RunnerConfig(), _landmark_kind)


def _run(be: TimedBackend, measurements: Iterable, fixes: FixSource, cfg: RunnerConfig, front, on_progress,
         observer: RunObserver | None = None, keep_truth: bool = True) -> RunResult:
    rec = RunRecorder(cfg.record_rate_hz, on_progress, cfg.rss_every_m, observer, keep_truth)
    heap = HeapTrim(cfg.trim_heap_every_s)
    outcomes: list[FixOutcome] = []
    kinds: dict[str, None] = {}  # the landmark kinds observed, in order of appearance
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i, m in enumerate(measurements):
        t = m.t
        rec.saw(t)
        for fix in fixes.due(t, be):  # deliver the fixes that are due
            for outcome in settle(outcomes, be.apply_fix(fix)):  # a held far fix decided later
                if observer is not None:
                    observer.fix(outcome)
        if isinstance(m, MOTION_INPUTS):
            step = front.motion(i, m)  # odometry corrected for slip and gyro bias
            if step is not None:  # predict
                be.predict(step)
                rec.predicted(t, be)
                fixes.after_predict(t, be)
                rec.progress(t)
                heap.tick(t)
        elif isinstance(m, GroundTruthPose):
            rec.saw_truth(m)
        else:  # observe
            kind = _landmark_kind(m, t)
            kinds.setdefault(kind)
            front.observe(kind, m)
            be.observe(m)
    if rec.t_first is None:
        raise RunnerError("the measurement stream is empty")
    if rec.n_predict == 0:
        raise RunnerError("the measurement stream has fewer than two IMU samples: nothing to predict")
    sent = fixes.sent(rec.t_last)
    final = be.trajectory()
    rec.sample_memory(rec.t_last)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    if on_progress is not None:
        on_progress(rec.t_last)
    return RunResult(
        backend=be.name, online=rec.online(), final=final, ground_truth=rec.ground_truth(),
        attempts=fixes.attempts, outcomes=outcomes, fixes_sent=sent,
        landmarks={k: be.landmark_map(k) for k in kinds}, stats=be.stats(),
        wall_s=wall, backend_s=be.busy_s, match_s=fixes.match_s, t_start=float(rec.t_first),
        t_end=float(rec.t_last), cpu_s=cpu, backend_cpu_s=be.busy_cpu_s,
        extra={"frame_latency": be.frame_latency.to_dict(), "frame_cpu_latency": be.frame_cpu_latency.to_dict(),
               "memory": rec.memory, "heap_trim": heap.stats(), **front.stats()},
    )

"""Runner: feed a time-ordered measurement stream to one back-end, with relocalization.

Per measurement: motion inputs go through :class:`reloc.odometry.OdometryAssembler` into
``predict``; rock frames into ``update_landmarks``; ground-truth poses are only collected for
evaluation. Fixes are delivered when the stream reaches their ``t_recv`` (before the measurement
at that time). Fixes come either from a :class:`Relocalizer` attempting every ``period_s`` on the
back-end's own map ("online"), or from a given list ("replay"): the comparison computes the fix
list once in a reference pass and replays the very same fixes to every back-end.

The run records the online estimate (with covariance) at ``record_rate_hz``, the final
``trajectory()``, every attempt and every fix outcome, and wall-clock timings.
"""

from __future__ import annotations

import heapq
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from ekf.blas import blas_limit
from fgslam.errors import FgslamError
from fgslam.relocalizer import FixAttempt, Relocalizer
from reloc.backend import Backend, BackendStats, FixOutcome, LandmarkMap, Trajectory
from reloc.config import NonNegativeInt, Positive, checked
from reloc.measurements import (
    CmdVel,
    GlobalFix,
    GroundTruthPose,
    ImuSample,
    RockObservations,
    WheelOdometry,
)
from reloc.odometry import OdometryAssembler

log = logging.getLogger(__name__)


class RunnerError(FgslamError):
    """The stream cannot be run (empty, no IMU, unknown measurement type)."""


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


@dataclass
class RunResult:
    """Everything one back-end pass produced (see module doc). Times in stream seconds."""

    backend: str
    online: Trajectory  # estimate as it was at the time, at record_rate_hz, with covariance
    final: Trajectory  # backend.trajectory() after the last input
    ground_truth: Trajectory | None
    attempts: list[FixAttempt]
    outcomes: list[FixOutcome]
    fixes_sent: list[GlobalFix]
    landmarks: LandmarkMap
    stats: BackendStats
    wall_s: float
    backend_s: float
    match_s: float
    t_start: float
    t_end: float
    extra: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start


def ground_truth_trajectory(poses: Sequence[GroundTruthPose]) -> Trajectory | None:
    """Stack ground-truth messages into a Trajectory (None when there are none)."""
    if not poses:
        return None
    t = np.array([g.t for g in poses])
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(np.array([g.quat_xyzw for g in poses])).as_matrix()
    T[:, :3, 3] = np.array([g.position_m for g in poses])
    return Trajectory(t, T, None)


def _stack(records: list) -> Trajectory:
    if not records:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)))
    return Trajectory(
        np.array([r.t for r in records]),
        np.array([r.T_world_base for r in records]),
        np.array([r.cov for r in records]),
    )


FEED_LOOKAHEAD_S = 5.0  # a replay asks its fix feed this far ahead of its stream time (> fix latency)


class FixFeed(Protocol):
    """Fixes that arrive while a run goes on (a reference pass producing them concurrently)."""

    def until(self, t: float) -> list[GlobalFix]:
        """Every not yet returned fix with ``t_recv <= t`` (blocks until that set is known)."""

    def rest(self) -> list[GlobalFix]:
        """Every not yet returned fix (blocks until the producer has finished)."""


FixSink = Callable[[str, object], None]  # ("fix", GlobalFix) for each new fix, ("time", t) as the stream advances


def run_backend(
    backend: Backend,
    measurements: Iterable,
    *,
    relocalizer: Relocalizer | None = None,
    fixes: Sequence[GlobalFix] | None = None,
    fix_feed: FixFeed | None = None,
    fix_sink: FixSink | None = None,
    config: RunnerConfig | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> RunResult:
    """Run ``backend`` over ``measurements`` (time-ordered). Give ``relocalizer`` (online fixes),
    ``fixes`` (replayed at their ``t_recv``) or ``fix_feed`` (the same, with the list still being
    produced), or none of them (no relocalization). ``fix_sink`` is told of every online fix and,
    about once per stream second, of how far the stream has got: no fix produced later can have
    ``t_recv`` before that time, which is what lets a :class:`FixFeed` consumer run alongside."""
    cfg = config or RunnerConfig()
    with blas_limit(cfg.blas_threads):
        return _run(backend, measurements, relocalizer, fixes, fix_feed, fix_sink, cfg, on_progress)


def _run(backend, measurements, relocalizer, fixes, fix_feed, fix_sink, cfg: RunnerConfig, on_progress) -> RunResult:
    if sum(x is not None for x in (relocalizer, fixes, fix_feed)) > 1:
        raise RunnerError("give one of a relocalizer (online fixes), a fix list or a fix feed (replay), not several")
    assembler = OdometryAssembler(speed_source=cfg.speed_source, max_gap_s=cfg.max_imu_gap_s,
                                  max_speed_age_s=cfg.max_speed_age_s)
    pending: list[tuple[float, int, GlobalFix]] = []
    for k, f in enumerate(fixes or ()):
        heapq.heappush(pending, (f.t_recv, k, f))
    # times the known fixes describe: a back-end that rolls back (the EKF) keeps a rollback point
    # there when told beforehand (expect_fix), so a late fix replays from t_meas, not from its
    # last periodic checkpoint
    expect = getattr(backend, "expect_fix", None)
    marks: list[float] = sorted(f.t_meas for f in fixes or ()) if expect is not None else []
    seq = len(pending)
    record_dt = 1.0 / cfg.record_rate_hz
    period = relocalizer.config.period_s if relocalizer is not None else np.inf
    online: list = []
    gt: list[GroundTruthPose] = []
    attempts: list[FixAttempt] = []
    outcomes: list[FixOutcome] = []
    sent: list[GlobalFix] = []
    backend_s = match_s = 0.0
    t_first = t_last = None
    next_record = next_attempt = None
    n_predict = 0
    fed: list[GlobalFix] = []
    feed_t = -np.inf  # the feed has been asked up to this stream time
    sink_t = -np.inf
    wall0 = time.perf_counter()
    for m in measurements:
        t = m.t
        if t_first is None:
            t_first = t
            next_record = t
            next_attempt = t + period
        t_last = t
        if fix_feed is not None and t > feed_t:
            # ask a little ahead, so that a fix's t_meas is known before the stream passes it
            for f in fix_feed.until(t + FEED_LOOKAHEAD_S):
                heapq.heappush(pending, (f.t_recv, seq, f))
                if expect is not None:
                    heapq.heappush(marks, f.t_meas)
                fed.append(f)
                seq += 1
            feed_t = t
        while marks and marks[0] < t:  # every input up to the fix time has been processed
            mark = heapq.heappop(marks)
            w0 = time.perf_counter()
            expect(mark)
            backend_s += time.perf_counter() - w0
        if fix_sink is not None and t >= sink_t + 1.0:
            fix_sink("time", t)
            sink_t = t
        while pending and pending[0][0] <= t:
            _, _, fix = heapq.heappop(pending)
            w0 = time.perf_counter()
            outcomes.append(backend.apply_fix(fix))
            backend_s += time.perf_counter() - w0
        if isinstance(m, (CmdVel, WheelOdometry, ImuSample)):
            step = assembler.push(m)
            if step is None:
                continue
            w0 = time.perf_counter()
            backend.predict(step)
            backend_s += time.perf_counter() - w0
            n_predict += 1
            if t >= next_record:
                online.append(backend.estimate())
                next_record = t_first + record_dt * (np.floor((t - t_first) / record_dt + 1e-9) + 1)
            if relocalizer is not None and t >= next_attempt:
                est = backend.estimate()
                att = None
                if relocalizer.wants(est):  # a rover standing still has nothing new to match
                    w0 = time.perf_counter()
                    att = relocalizer.attempt(backend.landmark_map(), est)
                    match_s += time.perf_counter() - w0
                    attempts.append(att)
                if att is not None and att.fix is not None:
                    if expect is not None:
                        expect(att.fix.t_meas)
                    heapq.heappush(pending, (att.fix.t_recv, seq, att.fix))
                    sent.append(att.fix)
                    seq += 1
                    if fix_sink is not None:
                        fix_sink("fix", att.fix)
                next_attempt = t_first + period * (np.floor((t - t_first) / period + 1e-9) + 1)
            if on_progress is not None and n_predict % 300 == 0:
                on_progress(t)
        elif isinstance(m, RockObservations):
            w0 = time.perf_counter()
            backend.update_landmarks(m)
            backend_s += time.perf_counter() - w0
        elif isinstance(m, GroundTruthPose):
            gt.append(m)
        else:
            raise RunnerError(f"the runner cannot consume {type(m).__name__} at t={t}")
    if t_first is None:
        raise RunnerError("the measurement stream is empty")
    if n_predict == 0:
        raise RunnerError("the measurement stream has fewer than two IMU samples: nothing to predict")
    if fixes is not None:
        sent = [f for f in fixes if f.t_recv <= t_last]
    if fix_feed is not None:
        fed.extend(fix_feed.rest())
        sent = [f for f in fed if f.t_recv <= t_last]
    w0 = time.perf_counter()
    final = backend.trajectory()
    backend_s += time.perf_counter() - w0
    wall = time.perf_counter() - wall0
    if on_progress is not None:
        on_progress(t_last)
    return RunResult(
        backend=getattr(backend, "name", type(backend).__name__),
        online=_stack(online),
        final=final,
        ground_truth=ground_truth_trajectory(gt),
        attempts=attempts,
        outcomes=outcomes,
        fixes_sent=sent,
        landmarks=backend.landmark_map(),
        stats=backend.stats(),
        wall_s=wall,
        backend_s=backend_s,
        match_s=match_s,
        t_start=float(t_first),
        t_end=float(t_last),
    )

"""Where a run's global fixes come from: one :class:`FixSource` beside the runner's loop.

- :class:`NoFixes`: none (odometry and landmarks only);
- :class:`OnlineFixes`: relocalizers attempting on the back-end's own maps, each on its own
  period of stream time; one relocalizer per landmark kind (it reads that kind's map) or one that
  combines several kinds (``kinds``), all in one source;
- :class:`ReplayedFixes`: a given list, delivered at each fix's ``t_recv`` (a comparison computes
  the list once, in a reference pass, and replays the very same fixes to every back-end);
- :class:`FedFixes`: the same while the list is still being produced (a reference pass running
  alongside, :class:`FixFeed`); asked a little ahead, so a fix's ``t_meas`` is known before the
  stream passes it.

A source is told of every measurement time (:meth:`FixSource.due`, before the measurement is
processed) and of every new estimate (:meth:`FixSource.after_predict`). Sources that know fixes
before they are due tell the back-end (``expect_fix``), so a back-end that rolls back keeps a
rollback point at each ``t_meas``.
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Protocol

import numpy as np

from fgslam.errors import FgslamError
from fgslam.relocalizer import FixAttempt
from reloc.backend import Backend, LandmarkMap, PoseEstimate
from reloc.kinds import KindLayerError, UnknownKindError, kind_named
from reloc.measurements import GlobalFix

FEED_LOOKAHEAD_S = 5.0  # a replay asks its fix feed this far ahead of its stream time (> fix latency)

FixSink = Callable[[str, object], None]  # ("fix", GlobalFix) for each new fix, ("time", t) as the stream advances


class FixSourceError(FgslamError):
    """Relocalizers cannot be built for the given catalogs."""


class FixProducer(Protocol):
    """A relocalizer: matches the back-end's maps of ``kinds`` every ``period_s`` of stream time
    (``config``: its resolved settings, a dataclass; ``build_time_s``: the wall time its catalog
    index took to build)."""

    kinds: tuple[str, ...]
    period_s: float
    config: object
    build_time_s: float

    def wants(self, est: PoseEstimate) -> bool:
        """Whether an attempt at ``est`` is worth making (the rover has moved)."""

    def attempt(self, maps: Mapping[str, LandmarkMap], est: PoseEstimate) -> FixAttempt:
        """Try to relocalize the maps (by kind) snapshotted with pose ``est`` (``t_meas = est.t``)."""


class WrappedProducer:
    """A relocalizer around another (``inner``): its kinds, period, config, build time,
    :meth:`wants` and any other attribute are ``inner``'s; subclasses change what :meth:`attempt`
    returns."""

    def __init__(self, inner: FixProducer) -> None:
        self.inner = inner

    @property
    def kinds(self) -> tuple[str, ...]:
        return self.inner.kinds

    @property
    def period_s(self) -> float:
        return self.inner.period_s

    @property
    def config(self) -> object:
        return self.inner.config

    @property
    def build_time_s(self) -> float:
        return self.inner.build_time_s

    def wants(self, est: PoseEstimate) -> bool:
        return self.inner.wants(est)

    def attempt(self, maps: Mapping[str, LandmarkMap], est: PoseEstimate) -> FixAttempt:
        return self.inner.attempt(maps, est)

    def __getattr__(self, name: str):  # the rest of the inner relocalizer (its catalog, counters) as it is
        if name == "inner":  # not set yet (copy, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)


def relocalizers_for(catalogs: Mapping[str, object], configs: Mapping[str, object] | None = None) -> list[FixProducer]:
    """One relocalizer per landmark kind with a catalog in ``catalogs`` (kind name -> catalog),
    built by that kind's relocalizer layer with ``configs[name]`` (None: its defaults); a kind
    without a relocalizer layer is an error, as is a config for a kind without a catalog."""
    configs = dict(configs or {})
    extra = sorted(set(configs) - set(catalogs))
    if extra:
        raise FixSourceError(f"relocalizer settings for {extra}, which have no catalog (catalogs: {sorted(catalogs)})")
    out = []
    for name, catalog in catalogs.items():
        try:
            factory = kind_named(name).layer("relocalizer")
        except (UnknownKindError, KindLayerError) as exc:
            raise FixSourceError(f"no relocalizer for the {name!r} catalog: {exc}") from None
        out.append(factory(catalog, configs.get(name)))
    return out


class FixFeed(Protocol):
    """Fixes that arrive while a run goes on (a reference pass producing them concurrently)."""

    def until(self, t: float) -> list[GlobalFix]:
        """Every not yet returned fix with ``t_recv <= t`` (blocks until that set is known)."""

    def rest(self) -> list[GlobalFix]:
        """Every not yet returned fix (blocks until the producer has finished)."""


class FixSource(Protocol):
    """One run's fixes (see module doc)."""

    attempts: list[FixAttempt]
    match_s: float

    def due(self, t: float, backend: Backend) -> list[GlobalFix]:
        """The stream has reached ``t``: the fixes with ``t_recv <= t`` not delivered yet, in order."""

    def after_predict(self, t: float, backend: Backend) -> None:
        """The back-end has a new estimate at ``t`` (online sources attempt here)."""

    def sent(self, t_end: float) -> list[GlobalFix]:
        """Every fix this run was given (``t_recv <= t_end``), in production order."""


class _Pending:
    """Fixes ordered by ``t_recv`` (ties: arrival order), and the ``t_meas`` still to announce."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, GlobalFix]] = []
        self._marks: list[float] = []
        self._seq = 0

    def push(self, fix: GlobalFix, announce: bool) -> None:
        heapq.heappush(self._heap, (fix.t_recv, self._seq, fix))
        self._seq += 1
        if announce:
            heapq.heappush(self._marks, fix.t_meas)

    def announce(self, t: float, backend: Backend) -> None:
        """Tell the back-end of every ``t_meas`` the stream is about to pass (all inputs before it
        have been processed)."""
        while self._marks and self._marks[0] < t:
            backend.expect_fix(heapq.heappop(self._marks))

    def pop_due(self, t: float) -> list[GlobalFix]:
        out = []
        while self._heap and self._heap[0][0] <= t:
            out.append(heapq.heappop(self._heap)[2])
        return out


class NoFixes:
    """No relocalization."""

    def __init__(self) -> None:
        self.attempts: list[FixAttempt] = []
        self.match_s = 0.0

    def due(self, t: float, backend: Backend) -> list[GlobalFix]:
        return []

    def after_predict(self, t: float, backend: Backend) -> None:
        return None

    def sent(self, t_end: float) -> list[GlobalFix]:
        return []


class ReplayedFixes(NoFixes):
    """A known fix list, each fix delivered when the stream reaches its ``t_recv``."""

    def __init__(self, fixes: Sequence[GlobalFix]) -> None:
        super().__init__()
        self._fixes = list(fixes)
        self._pending = _Pending()
        for f in self._fixes:
            self._pending.push(f, announce=True)

    def due(self, t: float, backend: Backend) -> list[GlobalFix]:
        self._pending.announce(t, backend)
        return self._pending.pop_due(t)

    def sent(self, t_end: float) -> list[GlobalFix]:
        return [f for f in self._fixes if f.t_recv <= t_end]


class FedFixes(NoFixes):
    """A fix list still being produced (:class:`FixFeed`), asked ``FEED_LOOKAHEAD_S`` ahead."""

    def __init__(self, feed: FixFeed) -> None:
        super().__init__()
        self._feed = feed
        self._fed: list[GlobalFix] = []
        self._asked_t = -np.inf  # the feed has been asked up to this stream time
        self._pending = _Pending()

    def due(self, t: float, backend: Backend) -> list[GlobalFix]:
        if t > self._asked_t:
            for f in self._feed.until(t + FEED_LOOKAHEAD_S):
                self._pending.push(f, announce=True)
                self._fed.append(f)
            self._asked_t = t
        self._pending.announce(t, backend)
        return self._pending.pop_due(t)

    def sent(self, t_end: float) -> list[GlobalFix]:
        self._fed.extend(self._feed.rest())
        return [f for f in self._fed if f.t_recv <= t_end]


class OnlineFixes(NoFixes):
    """Relocalizers on the back-end's own maps (see module doc). ``sink`` is told of every fix
    and, about once per stream second, of how far the stream has got: no fix produced later can
    have ``t_recv`` before that time, which lets a :class:`FixFeed` consumer run alongside."""

    def __init__(self, relocalizers: Iterable[FixProducer], sink: FixSink | None = None) -> None:
        super().__init__()
        self.relocalizers = list(relocalizers)
        self._sink = sink
        self._sink_t = -np.inf
        self._next: list[float] | None = None  # per relocalizer: stream time of its next attempt
        self._t0 = 0.0
        self._pending = _Pending()
        self._sent: list[GlobalFix] = []

    def due(self, t: float, backend: Backend) -> list[GlobalFix]:
        if self._next is None:  # the first measurement starts every relocalizer's schedule
            self._t0 = t
            self._next = [t + r.period_s for r in self.relocalizers]
        if self._sink is not None and t >= self._sink_t + 1.0:
            self._sink("time", t)
            self._sink_t = t
        return self._pending.pop_due(t)

    def after_predict(self, t: float, backend: Backend) -> None:
        est = None
        for i, r in enumerate(self.relocalizers):
            if t < self._next[i]:
                continue
            if est is None:
                est = backend.estimate()
            if r.wants(est):  # a rover standing still has nothing new to match
                w0 = time.perf_counter()
                att = r.attempt({k: backend.landmark_map(k) for k in r.kinds}, est)
                self.match_s += time.perf_counter() - w0
                self.attempts.append(att)
                if att.fix is not None:
                    backend.expect_fix(att.fix.t_meas)
                    self._pending.push(att.fix, announce=False)
                    self._sent.append(att.fix)
                    if self._sink is not None:
                        self._sink("fix", att.fix)
            p = r.period_s
            self._next[i] = self._t0 + p * (np.floor((t - self._t0) / p + 1e-9) + 1)

    def sent(self, t_end: float) -> list[GlobalFix]:
        return list(self._sent)

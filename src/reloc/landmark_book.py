"""Landmark bookkeeping shared by both back-ends: ids, observation counts, sizes, confirmation.

A new landmark is *tentative*; it is *confirmed* once observed ``confirm_n_obs`` times within
``confirm_window_s`` of its first sighting, and dropped if that window passes first (one-off
false detections never reach the map used for matching). When a back-end bounds its map, the
book chooses what to evict: landmarks not seen for the longest time, then the farthest, within
each kind's limit.

Entries are kept in insertion order, so row ``i`` of the book is row ``i`` of the back-end's
landmark arrays; every method that removes rows returns or takes a boolean keep mask. A book may
hold landmarks of several kinds (:mod:`reloc.kinds`): ``kind`` holds each one's kind code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.config import Positive, PositiveInt, checked


@dataclass(frozen=True)
@checked()
class LandmarkBookConfig:
    """Confirmation rule for tentative landmarks."""

    confirm_n_obs: PositiveInt = 3  # observations (the first included) needed to confirm
    confirm_window_s: Positive = 5.0  # ... within this many seconds of the first sighting


_COLUMNS = ("ids", "t_first", "t_last", "n_obs", "size_sum_m", "confirmed", "kind", "catalog_row")


class LandmarkBook:
    """Per-landmark records (N,): ``ids``, ``t_first``, ``t_last``, ``n_obs``, ``size_sum_m``,
    ``confirmed``, ``kind`` (the kind code, :func:`reloc.kinds.kind_code`), ``catalog_row`` (the
    catalog entry the landmark was anchored on, -1 for none)."""

    def __init__(self, config: LandmarkBookConfig | None = None) -> None:
        self.config = config or LandmarkBookConfig()
        self.next_id = 0
        self.ids = np.zeros(0, dtype=int)
        self.t_first = np.zeros(0)
        self.t_last = np.zeros(0)
        self.n_obs = np.zeros(0, dtype=int)
        self.size_sum_m = np.zeros(0)
        self.confirmed = np.zeros(0, dtype=bool)
        self.kind = np.zeros(0, dtype=np.int16)
        self.catalog_row = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def copy(self) -> LandmarkBook:
        """An independent copy (for filter checkpoints)."""
        other = LandmarkBook(self.config)
        other.next_id = self.next_id
        for name in _COLUMNS:
            setattr(other, name, getattr(self, name).copy())
        return other

    @property
    def size_m(self) -> np.ndarray:
        """(N,) mean observed diameter in metres."""
        return self.size_sum_m / np.maximum(self.n_obs, 1)

    def add(self, t: float, size_m: np.ndarray, kind: int = 0, n_obs: int = 1) -> np.ndarray:
        """Append ``len(size_m)`` tentative landmarks of kind code ``kind`` first seen at ``t``
        (``n_obs`` sightings of that size each: a landmark started from a first sighting and its
        repetition counts both); returns their ids (k,)."""
        size_m = np.reshape(np.asarray(size_m, dtype=float), (-1,))
        k = size_m.shape[0]
        new_ids = np.arange(self.next_id, self.next_id + k)
        self.next_id += k
        self.ids = np.concatenate([self.ids, new_ids])
        self.t_first = np.concatenate([self.t_first, np.full(k, t)])
        self.t_last = np.concatenate([self.t_last, np.full(k, t)])
        self.n_obs = np.concatenate([self.n_obs, np.full(k, n_obs, dtype=int)])
        self.size_sum_m = np.concatenate([self.size_sum_m, n_obs * size_m])
        self.confirmed = np.concatenate([self.confirmed, np.full(k, self.config.confirm_n_obs <= n_obs)])
        self.kind = np.concatenate([self.kind, np.full(k, kind, dtype=np.int16)])
        self.catalog_row = np.concatenate([self.catalog_row, np.full(k, -1, dtype=np.int64)])
        return new_ids

    def observe(self, rows: np.ndarray, t: float, size_m: np.ndarray) -> None:
        """Record one observation at ``t`` of the landmarks at ``rows`` (k,) with sizes (k,) m."""
        rows = np.asarray(rows, dtype=int)
        self.t_last[rows] = t
        self.n_obs[rows] += 1
        self.size_sum_m[rows] += np.asarray(size_m, dtype=float)
        ok = (self.n_obs[rows] >= self.config.confirm_n_obs) & (
            t - self.t_first[rows] <= self.config.confirm_window_s
        )
        self.confirmed[rows] |= ok

    def stale(self, t_now: float) -> np.ndarray:
        """(N,) bool: tentative landmarks whose confirmation window has passed at ``t_now``."""
        return ~self.confirmed & (t_now - self.t_first > self.config.confirm_window_s)

    def evictions(self, n_evict: int, distance_m: np.ndarray, protect: np.ndarray | None = None,
                  at_most: dict[int, int] | None = None) -> np.ndarray:
        """(N,) bool: the ``n_evict`` landmarks to drop, least recently seen first, then farthest
        (``distance_m`` (N,) from the rover); rows in ``protect`` (N,) bool are never chosen, and
        at most ``at_most[code]`` of kind ``code`` (a kind's landmarks beyond its reserved share;
        kinds not named are not limited)."""
        out = np.zeros(len(self), dtype=bool)
        if n_evict <= 0:
            return out
        allowed = np.ones(len(self), dtype=bool) if protect is None else ~np.asarray(protect, dtype=bool)
        rows = np.flatnonzero(allowed)
        rows = rows[np.lexsort((-np.asarray(distance_m)[rows], self.t_last[rows]))]
        for code, n in (at_most or {}).items():
            of = self.kind[rows] == code
            rows = rows[~of | (np.cumsum(of) <= n)]
        out[rows[:n_evict]] = True
        return out

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the rows where ``mask`` (N,) is True."""
        mask = np.asarray(mask, dtype=bool)
        for name in _COLUMNS:
            setattr(self, name, getattr(self, name)[mask])

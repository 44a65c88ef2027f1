"""Geometric hash of labelled triangles: quantised sorted sides + handedness -> triangle ids.

Keys are int64 ``(((hand * B + qa) * B + qb) * B + qc)`` with ``q = floor(side / bin_m)``; the table
is the sorted key array (one ``argsort`` at build time) plus the triangle ids in key order. Because
``qc`` is the fastest-varying part, all bins with fixed ``(hand, qa, qb)`` and ``qc`` in an interval
form one contiguous run, so a query with tolerance ``tol_m`` costs one pair of ``searchsorted`` calls
per ``(qa, qb)`` neighbour bin, fully vectorised over query triangles. Candidates from the
neighbouring bins are then filtered exactly (``|side - side'| <= tol`` for every side).
"""

from __future__ import annotations

import numpy as np

__all__ = ["TriangleHash"]

_B = np.int64(1 << 14)  # bins per side: sides up to 16384 * bin_m
_B_SMALL = np.int64(1 << 10)  # int32 keys: 1 + 3 * 10 bits


class TriangleHash:
    """Hash table over T triangles, held as their sorted int64 keys. Triangle ids are positions in
    key order: :meth:`build` returns the permutation that puts the caller's rows in that order."""

    def __init__(self, sorted_keys: np.ndarray, bin_m: float, bins: int = int(_B)) -> None:
        if not bin_m > 0.0:
            raise ValueError(f"hash bin_m must be positive, got {bin_m}")
        self.bin_m = float(bin_m)
        self.bins = np.int64(bins)
        self.keys = sorted_keys

    @classmethod
    def build(
        cls, sides_m: np.ndarray, handedness: np.ndarray, bin_m: float
    ) -> tuple[TriangleHash, np.ndarray]:
        """Hash of ``sides_m`` (T, 3) sorted, ``handedness`` (T,) in {-1, +1}, and the (T,)
        permutation from input rows to triangle ids (reorder per-triangle arrays with it)."""
        if not bin_m > 0.0:
            raise ValueError(f"hash bin_m must be positive, got {bin_m}")
        q = np.floor(sides_m / bin_m).astype(np.int64)
        # int32 keys (faster sort, half the memory) when every side has fewer than 1024 bins
        table = cls(np.empty(0, np.int64), bin_m, _B_SMALL if (q.size == 0 or q.max() < _B_SMALL) else _B)
        keys = table._keys(q, handedness)
        del q
        order = np.argsort(keys)  # deterministic for equal input
        table.keys = keys[order]
        return table, order

    def _keys(self, q: np.ndarray, hand: np.ndarray) -> np.ndarray:
        b = self.bins
        q = np.clip(q, 0, b - 1)
        h = (np.asarray(hand) > 0).astype(np.int64)
        keys = ((h * b + q[..., 0]) * b + q[..., 1]) * b + q[..., 2]
        return keys.astype(np.int32) if b == _B_SMALL else keys

    @property
    def nbytes(self) -> int:
        """Memory held by the table in bytes."""
        return int(self.keys.nbytes)

    def __len__(self) -> int:
        return int(self.keys.size)

    def _runs(
        self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Runs of the sorted keys touched by each query: (query index, start, count) per run."""
        sides_m = np.asarray(sides_m, dtype=float).reshape(-1, 3)
        empty = np.empty(0, np.int64)
        if sides_m.shape[0] == 0:
            return empty, empty, empty
        tol = np.broadcast_to(np.asarray(tol_m, dtype=float), (sides_m.shape[0],))[:, None]
        lo = np.floor((sides_m - tol) / self.bin_m).astype(np.int64)
        hi = np.floor((sides_m + tol) / self.bin_m).astype(np.int64)
        n_a = int(np.max(hi[:, 0] - lo[:, 0])) + 1
        n_b = int(np.max(hi[:, 1] - lo[:, 1])) + 1
        # every (qa, qb) neighbour bin of every query at once: (Q, n_a * n_b)
        da, db = np.meshgrid(np.arange(n_a), np.arange(n_b), indexing="ij")
        qa = lo[:, 0:1] + da.ravel()[None, :]
        qb = lo[:, 1:2] + db.ravel()[None, :]
        ok = (qa <= hi[:, 0:1]) & (qb <= hi[:, 1:2]) & (qa >= 0) & (qb >= 0)
        qidx = np.broadcast_to(np.arange(sides_m.shape[0])[:, None], qa.shape)[ok]
        qa, qb = qa[ok], qb[ok]
        hand = np.asarray(handedness)[qidx]
        start = np.stack([qa, qb, np.maximum(lo[qidx, 2], 0)], axis=1)
        stop = np.stack([qa, qb, hi[qidx, 2]], axis=1)
        starts = np.searchsorted(self.keys, self._keys(start, hand), "left")
        counts = np.searchsorted(self.keys, self._keys(stop, hand), "right") - starts
        return qidx, starts, counts

    def count(self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray) -> np.ndarray:
        """Number of triangles (Q,) in the bins :meth:`query` would return for each query."""
        qidx, _, counts = self._runs(sides_m, handedness, tol_m)
        n_q = np.asarray(sides_m).reshape(-1, 3).shape[0]
        return np.bincount(qidx, weights=counts, minlength=n_q).astype(np.int64)

    def query(
        self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Triangles within the bins touched by ``sides_m +- tol_m`` (Q, 3) with equal handedness.

        Returns ``(query_index, triangle_id)`` pairs (unfiltered by the exact tolerance; the caller
        compares sides, which it holds in float32 anyway).
        """
        qidx, starts, counts = self._runs(sides_m, handedness, tol_m)
        total = int(counts.sum())
        if total == 0:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        rep_q = np.repeat(qidx, counts)
        # positions start..start+count-1 for every run, without a Python loop
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        pos = np.repeat(starts, counts) + offsets
        return rep_q, pos

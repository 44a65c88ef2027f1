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


class TriangleHash:
    """Hash table over T triangles, held as their sorted int64 keys. Triangle ids are positions in
    key order: :meth:`build` returns the permutation that puts the caller's rows in that order."""

    def __init__(self, sorted_keys: np.ndarray, bin_m: float) -> None:
        if not bin_m > 0.0:
            raise ValueError(f"hash bin_m must be positive, got {bin_m}")
        self.bin_m = float(bin_m)
        self.keys = sorted_keys

    @classmethod
    def build(
        cls, sides_m: np.ndarray, handedness: np.ndarray, bin_m: float
    ) -> tuple[TriangleHash, np.ndarray]:
        """Hash of ``sides_m`` (T, 3) sorted, ``handedness`` (T,) in {-1, +1}, and the (T,)
        permutation from input rows to triangle ids (reorder per-triangle arrays with it)."""
        if not bin_m > 0.0:
            raise ValueError(f"hash bin_m must be positive, got {bin_m}")
        keys = cls._keys(np.floor(sides_m / bin_m).astype(np.int64), handedness)
        order = np.argsort(keys)  # deterministic for equal input
        return cls(keys[order], bin_m), order

    @staticmethod
    def _keys(q: np.ndarray, hand: np.ndarray) -> np.ndarray:
        q = np.clip(q, 0, _B - 1)
        h = (np.asarray(hand) > 0).astype(np.int64)
        return ((h * _B + q[..., 0]) * _B + q[..., 1]) * _B + q[..., 2]

    @property
    def nbytes(self) -> int:
        """Memory held by the table in bytes."""
        return int(self.keys.nbytes)

    def __len__(self) -> int:
        return int(self.keys.size)

    def query(
        self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Triangles within the bins touched by ``sides_m +- tol_m`` (Q, 3) with equal handedness.

        Returns ``(query_index, triangle_id)`` pairs (unfiltered by the exact tolerance; the caller
        compares sides, which it holds in float32 anyway).
        """
        sides_m = np.asarray(sides_m, dtype=float).reshape(-1, 3)
        tol = np.broadcast_to(np.asarray(tol_m, dtype=float), (sides_m.shape[0],))[:, None]
        lo = np.floor((sides_m - tol) / self.bin_m).astype(np.int64)
        hi = np.floor((sides_m + tol) / self.bin_m).astype(np.int64)
        n_a = int(np.max(hi[:, 0] - lo[:, 0])) + 1 if sides_m.size else 0
        n_b = int(np.max(hi[:, 1] - lo[:, 1])) + 1 if sides_m.size else 0
        if n_a == 0:
            return np.empty(0, np.int64), np.empty(0, np.int64)
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
        lo_parts = [np.searchsorted(self.keys, self._keys(start, hand), "left")]
        hi_parts = [np.searchsorted(self.keys, self._keys(stop, hand), "right")]
        qi_parts = [qidx]
        starts = np.concatenate(lo_parts)
        counts = np.concatenate(hi_parts) - starts
        qidx = np.concatenate(qi_parts)
        total = int(counts.sum())
        if total == 0:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        rep_q = np.repeat(qidx, counts)
        # positions start..start+count-1 for every run, without a Python loop
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        pos = np.repeat(starts, counts) + offsets
        return rep_q, pos

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

__all__ = ["TriangleHash", "expand_runs"]

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
        self._sat: tuple[np.ndarray, float] | None = None

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
        if keys.dtype == np.int32 and keys.size < (1 << 32):
            # one sort of (key, row) packed in int64: faster than an argsort and a gather
            packed = np.sort((keys.astype(np.int64) << 32) | np.arange(keys.size, dtype=np.int64))
            table.keys = (packed >> 32).astype(np.int32)
            return table, packed & np.int64(0xFFFFFFFF)
        order = np.argsort(keys, kind="stable")
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

    def runs(
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
        qidx, _, counts = self.runs(sides_m, handedness, tol_m)
        n_q = np.asarray(sides_m).reshape(-1, 3).shape[0]
        return np.bincount(qidx, weights=counts, minlength=n_q).astype(np.int64)

    def query(
        self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Triangles within the bins touched by ``sides_m +- tol_m`` (Q, 3) with equal handedness.

        Returns ``(query_index, triangle_id)`` pairs (unfiltered by the exact tolerance; the caller
        compares sides, which it holds in float32 anyway).
        """
        return expand_runs(*self.runs(sides_m, handedness, tol_m))

    def estimate_count(
        self, sides_m: np.ndarray, handedness: np.ndarray, tol_m: float | np.ndarray
    ) -> np.ndarray:
        """Approximate :meth:`count` (Q,) float from a coarse 3D histogram of the keys (cells of
        ``coarse_bins`` hash bins, summed-area table built on first use): O(1) per query, for
        ranking queries by how common their shape is."""
        if self._sat is None:
            self._sat = self._summed_area()
        sat, cell = self._sat
        sides_m = np.asarray(sides_m, dtype=float).reshape(-1, 3)
        tol = np.broadcast_to(np.asarray(tol_m, dtype=float), (sides_m.shape[0],))[:, None]
        top = sat.shape[1] - 1
        lo = np.clip(np.floor((sides_m - tol) / cell).astype(np.int64), 0, top)
        hi = np.clip(np.floor((sides_m + tol) / cell).astype(np.int64) + 1, 0, top)
        h = (np.asarray(handedness) > 0).astype(np.int64)
        total = np.zeros(sides_m.shape[0])
        for corner in range(8):  # inclusion-exclusion over the box corners
            pick = [(hi if corner >> d & 1 else lo)[:, d] for d in range(3)]
            sign = (-1.0) ** (3 - corner.bit_count())
            total += sign * sat[h, pick[0], pick[1], pick[2]]
        # the box holds whole cells: scale by the fraction of its volume the query covers
        frac = np.prod(np.minimum(1.0, 2.0 * tol / np.maximum((hi - lo) * cell, 1e-12)), axis=1)
        return np.maximum(total, 0.0) * frac

    def _summed_area(self, coarse_bins: int = 4, max_cells: int = 64) -> tuple[np.ndarray, float]:
        b = int(self.bins)
        keys = self.keys.astype(np.int64)
        q = np.stack([keys // (b * b) % b, keys // b % b, keys % b], axis=1) // coarse_bins
        hand = keys // (b * b * b)
        q = np.minimum(q, max_cells - 1)
        hist = np.zeros((2, max_cells, max_cells, max_cells), np.int64)
        np.add.at(hist, (hand, q[:, 0], q[:, 1], q[:, 2]), 1)
        # int32 where the counts fit: the table (2 x 65^3 cells) is kept per hash, and a relocalizer
        # keeps a crop's hash per cached crop (8 per kind): 33.5 MB of int64 tables on a kilometre run
        dtype = np.int32 if keys.size < np.iinfo(np.int32).max else np.int64
        sat = np.zeros((2, max_cells + 1, max_cells + 1, max_cells + 1), dtype)
        sat[:, 1:, 1:, 1:] = hist.cumsum(1).cumsum(2).cumsum(3)
        return sat, coarse_bins * self.bin_m


def expand_runs(
    qidx: np.ndarray, starts: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(query index, position) of every key in the runs of :meth:`TriangleHash.runs`."""
    total = int(counts.sum())
    if total == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    rep_q = np.repeat(qidx, counts)
    # positions start..start+count-1 for every run, without a Python loop
    offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    pos = np.repeat(starts, counts) + offsets
    return rep_q, pos

"""Scoring a pose hypothesis: one-to-one inliers, RMSE, and the chance of that many inliers.

Inliers are local rocks whose transformed position lies within ``radius_m`` of a catalog rock,
each catalog rock claimed at most once (by its closest local rock). A random pose puts each local
rock within ``radius_m`` of some catalog rock with probability ``p = 1 - exp(-rho pi r^2)``
(Poisson field of density ``rho``), so the inlier count of a wrong pose is Binomial(n, p). The
acceptance statistic is the log10 binomial tail of the observed count, plus log10 of the number of
hypotheses tried (a Bonferroni bound on the expected number of false alarms in the search).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import gammaln

__all__ = [
    "CoarseScorer",
    "Inliers",
    "chance_probability",
    "log10_binomial_tail",
    "log10_poisson_binomial_tail",
    "score_points",
    "size_compatible_fraction",
]


@dataclass(frozen=True, slots=True)
class Inliers:
    """One-to-one inliers: ``local_idx`` (K,), ``catalog_idx`` (K,), ``dist_m`` (K,)."""

    local_idx: np.ndarray
    catalog_idx: np.ndarray
    dist_m: np.ndarray

    @property
    def count(self) -> int:
        return int(self.local_idx.size)

    @property
    def rmse_m(self) -> float:
        """Root mean square inlier distance (inf without inliers)."""
        return float(np.sqrt(np.mean(self.dist_m**2))) if self.count else math.inf


def score_points(
    tree: cKDTree,
    world_xy: np.ndarray,
    radius_m: float,
    size_check: tuple[np.ndarray, np.ndarray, float] | None = None,
    *,
    k: int = 4,
) -> Inliers:
    """Inliers of transformed local points ``world_xy`` (M, 2) against the catalog ``tree``.

    ``size_check = (local_log_size (M,), catalog_log_size (N,), log_tol)``: a pair also needs
    ``|log size ratio| <= log_tol`` to count (a random pair rarely agrees in size as well). Each
    local point pairs with the nearest size-compatible catalog rock among its ``k`` nearest within
    the radius (in a cluster the nearest rock is often another one), which is the event the chance
    model of :meth:`~reloc.matcher.ConstellationMatcher` counts: "some compatible rock within r".
    """
    if size_check is None or k <= 1:
        dist, idx = tree.query(world_xy, k=1, distance_upper_bound=radius_m)
        if size_check is not None:
            loc_ls, cat_ls, tol = size_check
            hit = np.flatnonzero(dist <= radius_m)
            dist[hit[np.abs(loc_ls[hit] - cat_ls[idx[hit]]) > tol]] = np.inf
        return one_to_one(dist, idx, radius_m)
    loc_ls, cat_ls, tol = size_check
    dist, idx = tree.query(world_xy, k=k, distance_upper_bound=radius_m)
    near = dist <= radius_m
    rows, cols = np.nonzero(near)
    bad = np.abs(loc_ls[rows] - cat_ls[idx[rows, cols]]) > tol
    dist[rows[bad], cols[bad]] = np.inf
    # columns are sorted by distance: the first finite one is the nearest compatible rock
    first = np.argmin(~np.isfinite(dist), axis=1)
    m = np.arange(dist.shape[0])
    return one_to_one(dist[m, first], idx[m, first], radius_m)


def one_to_one(dist: np.ndarray, idx: np.ndarray, radius_m: float) -> Inliers:
    """Keep, for each catalog rock, only its closest local rock among those within ``radius_m``."""
    local = np.flatnonzero(dist <= radius_m)
    if local.size == 0:
        empty = np.empty(0, np.int64)
        return Inliers(empty, empty, np.empty(0))
    d = dist[local]
    cat = idx[local]
    if np.unique(cat).size == cat.size:  # no catalog rock claimed twice (the usual case)
        return Inliers(local, cat.astype(np.int64), d)
    order = np.lexsort((d, cat))
    first = np.ones(order.size, bool)
    first[1:] = cat[order][1:] != cat[order][:-1]
    keep = np.sort(order[first])
    return Inliers(local[keep], cat[keep].astype(np.int64), d[keep])


def chance_probability(density_per_m2: float, radius_m: float, size_fraction: float = 1.0) -> float:
    """Probability that a random point lies within ``radius_m`` of some rock of a Poisson field of
    density ``density_per_m2``, of which only ``size_fraction`` have a compatible size."""
    return float(-math.expm1(-density_per_m2 * size_fraction * math.pi * radius_m * radius_m))


def size_compatible_fraction(local_log_size: np.ndarray, catalog_log_size_sorted: np.ndarray, log_tol: float) -> float:
    """Mean over local rocks of the fraction of catalog rocks whose log size is within ``log_tol``."""
    return float(np.mean(size_compatible_fractions(local_log_size, catalog_log_size_sorted, log_tol)))


def size_compatible_fractions(
    local_log_size: np.ndarray, catalog_log_size_sorted: np.ndarray, log_tol: float
) -> np.ndarray:
    """Per local rock (M,): the fraction of catalog rocks whose log size is within ``log_tol``."""
    lo = np.searchsorted(catalog_log_size_sorted, local_log_size - log_tol, "left")
    hi = np.searchsorted(catalog_log_size_sorted, local_log_size + log_tol, "right")
    return (hi - lo) / max(catalog_log_size_sorted.size, 1)


def log10_binomial_tail(k: int, n: int, p: float) -> float:
    """log10 P(X >= k) for X ~ Binomial(n, p), exact and without underflow (0 when k <= 0)."""
    if k <= 0:
        return 0.0
    if k > n:
        return -math.inf
    p = min(max(p, 1e-300), 1.0 - 1e-16)
    j = np.arange(k, n + 1, dtype=float)
    logpmf = gammaln(n + 1) - gammaln(j + 1) - gammaln(n - j + 1) + j * math.log(p) + (n - j) * math.log1p(-p)
    top = float(np.max(logpmf))
    return (top + math.log(float(np.sum(np.exp(logpmf - top))))) / math.log(10.0)


def log10_poisson_binomial_tail(k: int, p: np.ndarray) -> float:
    """log10 P(X >= k) for X the number of successes of independent trials with chances ``p`` (n,).

    Exact (dynamic programme over the trials, O(n k)); 0 when k <= 0, -inf when k > n. With
    equal chances it equals :func:`log10_binomial_tail`; with unequal ones it is never larger
    than the binomial tail at the mean chance once k exceeds the mean by one (Hoeffding 1956).
    """
    p = np.clip(np.asarray(p, dtype=float).ravel(), 0.0, 1.0)
    if k <= 0:
        return 0.0
    if k > p.size:
        return -math.inf
    # natural logs of P(j successes so far) for j < k, and of P(k or more so far)
    with np.errstate(divide="ignore"):
        log_p, log_q = np.log(p), np.log1p(-p)
    dist = np.full(k, -np.inf)
    dist[0] = 0.0
    tail = -np.inf
    for lp, lq in zip(log_p, log_q):
        tail = np.logaddexp(tail, dist[-1] + lp)
        dist[1:] = np.logaddexp(dist[1:] + lq, dist[:-1] + lp)
        dist[0] += lq
    return float(tail) / math.log(10.0)


class CoarseScorer:
    """Counts, for many poses at once, the local rocks that land near a size-compatible catalog rock.

    A dense grid over the catalog (cell ``cell_m``) holds one bit per size class (8 classes over
    the catalog's log sizes) for every cell that a catalog rock of that class comes within
    ``radius_m`` of. Scoring H poses of M rocks is then H x M grid reads: cheap enough to rank
    every hypothesis before the exact (KD-tree) verification of the best ones. The grid is
    conservative (a cell is marked when any of its points is within the radius), so a local rock
    within ``radius_m`` of a compatible catalog rock always counts.
    """

    def __init__(
        self,
        xy_m: np.ndarray,
        log_size: np.ndarray,
        radius_m: float,
        log_tol: float | None,
        *,
        max_cells: int = 1 << 25,
    ) -> None:
        xy_m = np.asarray(xy_m, float)
        self.log_tol = log_tol
        self.origin = xy_m.min(axis=0) - radius_m
        span = np.ptp(xy_m, axis=0) + 2.0 * radius_m
        cell = radius_m / 4.0
        cell = max(cell, float(np.sqrt(span[0] * span[1] / max_cells)))
        self.cell_m = cell
        self.shape = (int(span[0] // cell) + 1, int(span[1] // cell) + 1)
        ls = np.asarray(log_size, float)
        # 8 classes over the central 98 % of log sizes (the outer classes take the rest)
        q_lo, q_hi = np.percentile(ls, [1.0, 99.0])
        self.class_lo = float(q_lo)
        self.class_w = max(float(q_hi - q_lo) / 8.0, 1e-9)
        cls = np.clip(((ls - self.class_lo) / self.class_w).astype(np.int64), 0, 7)
        grid = np.zeros(self.shape[0] * self.shape[1], np.uint8)
        reach = int(np.ceil(radius_m / cell + 0.7072)) + 1
        oi, oj = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
        ij = np.floor((xy_m - self.origin) / cell).astype(np.int64)
        for di, dj in zip(oi.ravel(), oj.ravel()):
            # distance from the rock to the nearest point of cell (i+di, j+dj)
            ci, cj = ij[:, 0] + di, ij[:, 1] + dj
            ex = np.maximum(0.0, np.maximum(ci * cell - (xy_m[:, 0] - self.origin[0]), (xy_m[:, 0] - self.origin[0]) - (ci + 1) * cell))
            ey = np.maximum(0.0, np.maximum(cj * cell - (xy_m[:, 1] - self.origin[1]), (xy_m[:, 1] - self.origin[1]) - (cj + 1) * cell))
            ok = (ex * ex + ey * ey <= radius_m * radius_m) & (ci >= 0) & (cj >= 0)
            ok &= (ci < self.shape[0]) & (cj < self.shape[1])
            flat = ci[ok] * self.shape[1] + cj[ok]
            bits = (np.uint8(1) << cls[ok].astype(np.uint8)).astype(np.uint8)
            for b in range(8):  # repeated cells: assignment of one bit is idempotent
                sel = bits == (1 << b)
                if np.any(sel):
                    grid[flat[sel]] |= np.uint8(1 << b)
        self.grid = grid

    @property
    def nbytes(self) -> int:
        """Bytes of the grid."""
        return int(self.grid.nbytes)

    def masks(self, local_log_size: np.ndarray | None, n: int) -> np.ndarray:
        """Size-class masks (n,) uint8 of the local rocks: the classes within ``log_tol`` of each."""
        if local_log_size is None or self.log_tol is None:
            return np.full(n, 0xFF, np.uint8)
        ls = np.asarray(local_log_size, float)
        lo = np.floor((ls - self.log_tol - self.class_lo) / self.class_w).astype(np.int64)
        hi = np.floor((ls + self.log_tol - self.class_lo) / self.class_w).astype(np.int64)
        lo, hi = np.clip(lo, 0, 7), np.clip(hi, 0, 7)
        bits = np.arange(8)
        sel = (bits[None, :] >= lo[:, None]) & (bits[None, :] <= hi[:, None])
        return (sel * (1 << bits)[None, :]).sum(axis=1).astype(np.uint8)

    def score(
        self,
        theta_rad: np.ndarray,
        scale: np.ndarray,
        translation: np.ndarray,
        local_xy: np.ndarray,
        masks: np.ndarray,
        chunk: int = 1 << 20,
    ) -> np.ndarray:
        """Rocks (H,) of ``local_xy`` (M, 2) within the radius of a compatible catalog rock under
        each of H poses ``world = scale R(theta) local + translation``."""
        h = theta_rad.size
        out = np.zeros(h, np.int64)
        m = local_xy.shape[0]
        if h == 0 or m == 0:
            return out
        step = max(1, chunk // m)
        lx = (local_xy[:, 0] / self.cell_m)[None, :]
        ly = (local_xy[:, 1] / self.cell_m)[None, :]
        for a in range(0, h, step):
            b = min(h, a + step)
            sc = scale[a:b, None]
            c, s = sc * np.cos(theta_rad[a:b, None]), sc * np.sin(theta_rad[a:b, None])
            tx = ((translation[a:b, 0] - self.origin[0]) / self.cell_m)[:, None]
            ty = ((translation[a:b, 1] - self.origin[1]) / self.cell_m)[:, None]
            ci = np.floor(c * lx - s * ly + tx).astype(np.int64)
            cj = np.floor(s * lx + c * ly + ty).astype(np.int64)
            inside = (ci >= 0) & (cj >= 0) & (ci < self.shape[0]) & (cj < self.shape[1])
            flat = np.where(inside, ci * self.shape[1] + cj, 0)
            hit = (np.take(self.grid, flat) & masks[None, :]) != 0
            out[a:b] = np.count_nonzero(hit & inside, axis=1)
        return out

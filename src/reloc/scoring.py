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
    "Inliers",
    "chance_probability",
    "log10_binomial_tail",
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
) -> Inliers:
    """Inliers of transformed local points ``world_xy`` (M, 2) against the catalog ``tree``.

    ``size_check = (local_log_size (M,), catalog_log_size (N,), log_tol)``: a pair also needs
    ``|log size ratio| <= log_tol`` to count (a random pair rarely agrees in size as well).
    """
    dist, idx = tree.query(world_xy, k=1, distance_upper_bound=radius_m)
    if size_check is not None:
        loc_ls, cat_ls, tol = size_check
        hit = np.flatnonzero(dist <= radius_m)
        bad = hit[np.abs(loc_ls[hit] - cat_ls[idx[hit]]) > tol]
        dist[bad] = np.inf
    return one_to_one(dist, idx, radius_m)


def one_to_one(dist: np.ndarray, idx: np.ndarray, radius_m: float) -> Inliers:
    """Keep, for each catalog rock, only its closest local rock among those within ``radius_m``."""
    local = np.flatnonzero(dist <= radius_m)
    if local.size == 0:
        empty = np.empty(0, np.int64)
        return Inliers(empty, empty, np.empty(0))
    d = dist[local]
    cat = idx[local]
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
    lo = np.searchsorted(catalog_log_size_sorted, local_log_size - log_tol, "left")
    hi = np.searchsorted(catalog_log_size_sorted, local_log_size + log_tol, "right")
    return float(np.mean(hi - lo) / max(catalog_log_size_sorted.size, 1))


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

"""Synthetic rock fields and local-map queries for the matcher benchmark (seeded, no I/O).

Fields have a density of 0.3 rocks/m^2 (the planning measurements) over a square, uniform or
clustered (Thomas process: Gaussian clusters of ~15 rocks, sigma 3 m, plus 20 % background).
Rock diameters are log-normal (median 0.3 m, log-sigma 0.5).

A query takes the catalog rocks nearest to a random point (a disc holding ``n_local`` rocks),
drops a fraction, adds spurious rocks inside the disc, jitters positions by ``sigma_m`` and
sizes by ``size_jitter`` (log-normal), and moves the result by a random rigid transform. The
truth is ``world = R(theta) @ local + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Field", "Query", "detector_catalog", "detector_query", "make_field", "make_query", "runner_query"]

DENSITY_PER_M2 = 0.3
MEDIAN_SIZE_M = 0.3
LOG_SIZE_SIGMA = 0.5


@dataclass(frozen=True)
class Field:
    """Rocks ``xy`` (N, 2) metres in a square of side ``side_m`` with origin at ``origin``, diameters ``size`` (N,)."""

    xy: np.ndarray
    size: np.ndarray
    side_m: float
    origin: np.ndarray


@dataclass(frozen=True)
class Query:
    """A local map and its truth: ``world = R(theta_rad) @ local + t``; ``center_world`` (2,) is the disc centre."""

    local_xy: np.ndarray
    local_size: np.ndarray
    theta_rad: float
    t: np.ndarray
    center_world: np.ndarray


def _sizes(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.lognormal(np.log(MEDIAN_SIZE_M), LOG_SIZE_SIGMA, n)


def make_field(n: int, layout: str, rng: np.random.Generator, origin: tuple[float, float] = (0.0, 0.0)) -> Field:
    """``n`` rocks, ``layout`` "uniform" or "clustered", density 0.3 rocks/m^2."""
    side = float(np.sqrt(n / DENSITY_PER_M2))
    org = np.asarray(origin, float)
    if layout == "uniform":
        xy = rng.uniform(0.0, side, (n, 2))
    elif layout == "clustered":
        n_bg = n // 5
        n_cl = n - n_bg
        n_parents = max(1, n_cl // 15)
        parents = rng.uniform(0.0, side, (n_parents, 2))
        kids = parents[rng.integers(0, n_parents, n_cl)] + rng.normal(0.0, 3.0, (n_cl, 2))
        kids = np.abs(kids)  # reflect at the borders so the square keeps all rocks
        kids = side - np.abs(side - kids)
        xy = np.vstack([rng.uniform(0.0, side, (n_bg, 2)), kids])
    else:
        raise ValueError(f"unknown layout {layout!r} (uniform, clustered)")
    return Field(xy + org, _sizes(rng, n), side, org)


def _random_rigid(rng: np.random.Generator, center: np.ndarray) -> tuple[float, np.ndarray]:
    theta = float(rng.uniform(-np.pi, np.pi))
    t = center + rng.uniform(-30.0, 30.0, 2)
    return theta, t


def _to_local(world_xy: np.ndarray, theta: float, t: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return (world_xy - t) @ rot  # R^T (w - t), row-wise


def _disc_center(field: Field, rng: np.random.Generator, margin_m: float) -> np.ndarray:
    m = min(margin_m, 0.45 * field.side_m)
    return field.origin + rng.uniform(m, field.side_m - m, 2)


def make_query(
    field: Field,
    rng: np.random.Generator,
    sigma_m: float,
    *,
    n_local: int = 40,
    drop: float = 0.3,
    spurious: float = 0.1,
    size_jitter: float = 0.15,
    tree=None,
) -> Query:
    """A local map cut from ``field`` (``tree``: a cKDTree over ``field.xy``, built if None)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(field.xy)
    center = _disc_center(field, rng, margin_m=8.0)
    dist, idx = tree.query(center, k=min(n_local, field.xy.shape[0]))
    radius = float(np.max(dist))
    keep = idx[rng.random(idx.size) >= drop]
    return _observed(rng, center, radius, field.xy[keep], field.size[keep], round(spurious * n_local), sigma_m, size_jitter)


def _observed(rng: np.random.Generator, center: np.ndarray, radius: float, xy: np.ndarray, size: np.ndarray,
              n_fake: int, sigma_m: float, size_jitter: float) -> Query:
    """A local map of the rocks ``xy`` (K, 2), ``size`` (K,) seen with noise, plus ``n_fake`` false
    rocks in the disc (``center``, ``radius``), shuffled and moved by a random rigid transform."""
    ang = rng.uniform(0.0, 2 * np.pi, n_fake)
    rr = radius * np.sqrt(rng.random(n_fake))
    fake_xy = center + np.stack([rr * np.cos(ang), rr * np.sin(ang)], axis=1)
    world = np.vstack([xy + rng.normal(0.0, sigma_m, (xy.shape[0], 2)), fake_xy])
    sizes = np.concatenate([size * np.exp(rng.normal(0.0, size_jitter, size.shape[0])), _sizes(rng, n_fake)])
    perm = rng.permutation(world.shape[0])
    theta, t = _random_rigid(rng, center)
    return Query(_to_local(world[perm], theta, t), sizes[perm], theta, t, center)


def detector_catalog(
    truth: Field, rng: np.random.Generator, *, precision: float, recall: float, sigma_m: float, size_jitter: float
) -> Field:
    """What an orbital detector of the given precision/recall reports of ``truth``."""
    hit = rng.random(truth.xy.shape[0]) < recall
    n_tp = int(hit.sum())
    n_fp = round(n_tp * (1.0 - precision) / precision)
    xy = np.vstack(
        [truth.xy[hit] + rng.normal(0.0, sigma_m, (n_tp, 2)), truth.origin + rng.uniform(0.0, truth.side_m, (n_fp, 2))]
    )
    size = np.concatenate([truth.size[hit] * np.exp(rng.normal(0.0, size_jitter, n_tp)), _sizes(rng, n_fp)])
    perm = rng.permutation(xy.shape[0])
    return Field(xy[perm], size[perm], truth.side_m, truth.origin)


def detector_query(
    truth: Field,
    rng: np.random.Generator,
    *,
    n_local: int,
    precision: float,
    recall: float,
    sigma_m: float,
    size_jitter: float,
    tree=None,
) -> Query:
    """A local map of about ``n_local`` detections made by a rover detector of the given quality."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(truth.xy)
    n_true = round(n_local * precision / recall)
    center = _disc_center(truth, rng, margin_m=11.0)
    dist, idx = tree.query(center, k=min(n_true, truth.xy.shape[0]))
    radius = float(np.max(dist))
    hit = idx[rng.random(idx.size) < recall]
    n_fp = round(hit.size * (1.0 - precision) / precision)
    return _observed(rng, center, radius, truth.xy[hit], truth.size[hit], n_fp, sigma_m, size_jitter)


def runner_query(
    field: Field,
    rng: np.random.Generator,
    sigma_m: float,
    *,
    n_local: int = 100,
    drift_m: float = 1.5,
    drift_yaw_rad: float = 0.05,
    tree=None,
) -> Query:
    """A local map as the runner matches it: the ``n_local`` rocks of a disc, 30 % dropped,
    10 % spurious added (about 80 rocks for 100), jittered by ``sigma_m``, in the rover's estimated world frame, which is off from the true
    one by a small drift (``drift_m`` per axis, ``drift_yaw_rad`` standard deviations)."""
    q = make_query(field, rng, sigma_m, n_local=n_local, tree=tree)
    # back to world coordinates, then into a drifted estimate of the world frame
    c, s = np.cos(q.theta_rad), np.sin(q.theta_rad)
    world = q.local_xy @ np.array([[c, s], [-s, c]]) + q.t
    theta = float(rng.normal(0.0, drift_yaw_rad))
    t = rng.normal(0.0, drift_m, 2) + (world.mean(axis=0) - _rot(theta) @ world.mean(axis=0))
    return Query(_to_local(world, theta, t), q.local_size, theta, t, q.center_world)


def _rot(theta: float) -> np.ndarray:
    return np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])

"""Orbital rock catalog: the rocks a nadir image detector would report.

A rock smaller than ``min_size_px`` ground samples is never found; above that, the detection
probability is a logistic in log(size) whose midpoint is solved so that the expected share of
true rocks found equals the configured recall (bigger rocks first). Positions get Gaussian noise
of ``sigma_position_px`` ground samples, sizes a relative log-normal error; false positives
(rock-like ground features) are spread over the world so that true / all entries equals the
configured precision.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from reloc.measurements import RockCatalog
from sim.config import OrbitalConfig, resolve_orbital
from sim.world import World

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CatalogTruth:
    """The catalog and, per entry, the true rock row it came from (-1: false positive)."""

    catalog: RockCatalog
    rock: np.ndarray


def orbital_detection_probability(size_m: np.ndarray, cfg: OrbitalConfig) -> np.ndarray:
    """Probability (R,) that the nadir detector finds each rock of diameter ``size_m`` (R,); the
    mean over ``size_m`` (``recall_basis`` "all") or over its rocks of ``min_size_px`` and more
    ("detectable") is the configured recall."""
    return detection_curve(size_m, cfg)(size_m)


def detection_curve(size_m: np.ndarray, cfg: OrbitalConfig):
    """The detector's probability of detection as a function of rock diameter (m): zero below
    ``min_size_px``, above it a logistic in log size whose midpoint is solved so that the expected
    recall over the population ``size_m`` (R,) is the configured one."""
    cfg = resolve_orbital(cfg)
    def detectable(d):
        return np.asarray(d, dtype=float) / cfg.gsd_m >= cfg.min_size_px

    seen = detectable(size_m)
    if not np.any(seen):
        return lambda d: np.zeros(len(d))
    target = cfg.recall * (seen.sum() if cfg.recall_basis == "detectable" else len(size_m))
    if target >= seen.sum():
        if cfg.recall < 1.0:
            log.warning("orbital recall %.3f needs rocks below min_size_px; all visible rocks are found", cfg.recall)
        return lambda d: detectable(d).astype(float)
    x = np.log(size_m[seen]) / cfg.detect_size_width_rel

    def gap(c: float) -> float:
        return float(np.sum(1.0 / (1.0 + np.exp(-(x - c))))) - target

    c = brentq(gap, x.min() - 60.0, x.max() + 60.0, xtol=1e-8)

    def p_of(d):
        d = np.asarray(d, dtype=float)
        p = np.zeros(len(d))
        ok = detectable(d)
        p[ok] = 1.0 / (1.0 + np.exp(-(np.log(d[ok]) / cfg.detect_size_width_rel - c)))
        return p

    return p_of


def simulate_catalog(world: World, cfg: OrbitalConfig, rng: np.random.Generator) -> CatalogTruth:
    """A :class:`RockCatalog` of ``world`` (world-frame x, y, diameter, score) as seen from orbit."""
    cfg = resolve_orbital(cfg)
    rocks = world.rocks
    p = orbital_detection_probability(rocks.size_m, cfg)
    found = np.flatnonzero(rng.random(len(rocks)) < p)
    sigma_xy = cfg.gsd_m * cfg.sigma_position_px
    xy = rocks.xyz_m[found, :2] + sigma_xy * rng.standard_normal((len(found), 2))
    size = rocks.size_m[found] * np.exp(cfg.size_sigma_rel * rng.standard_normal(len(found)))
    score = rng.beta(6.0, 3.0, len(found))
    n_fp = rng.poisson(len(found) * (1.0 - cfg.precision) / cfg.precision) if cfg.precision < 1.0 else 0
    xmin, xmax, ymin, ymax = world.extent
    fp_xy = np.column_stack([rng.uniform(xmin, xmax, n_fp), rng.uniform(ymin, ymax, n_fp)])
    # false positives look like the rocks the detector does find (else a size filter removes them)
    pool = rocks.size_m[found] if len(found) else np.array([max(cfg.min_size_px * cfg.gsd_m, 0.1)])
    fp_size = rng.choice(pool, n_fp) * np.exp(0.3 * rng.standard_normal(n_fp))
    fp_score = rng.beta(3.0, 4.0, n_fp)
    catalog = RockCatalog(
        xy_m=np.vstack([xy, fp_xy]),
        size_m=np.maximum(np.concatenate([size, fp_size]), 1e-3),
        score=np.concatenate([score, fp_score]),
    )
    order = rng.permutation(len(catalog))  # entries carry no hint of which are false
    catalog = RockCatalog(catalog.xy_m[order], catalog.size_m[order], catalog.score[order])
    truth = np.concatenate([found, np.full(n_fp, -1)])[order]
    return CatalogTruth(catalog, truth)

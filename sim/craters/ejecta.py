"""Ejecta blocks: the rocks thrown out by fresh craters that reached below the regolith.

A crater of rim diameter D >= ``min_crater_diameter_m`` and degradation below
``fresh_degradation`` carries blocks. The largest block is L_max = a D^b (a = 0.29, b = 0.7, D and
L in metres: the lunar and martian boulder scaling of Moore 1971 and Bart & Melosh 2010 puts it
near 0.25-0.3 D^(2/3)); block sizes follow a cumulative power law N(>L) = (L / L_max)^-s
(s = 2.5) on [min_block_m, min(L_max, max_block_m)], their number scaled down linearly as the
crater degrades (buried and broken). Surface density falls as (r / R)^-3 from
``inner_radius`` to ``outer_radius`` crater radii, like the ejecta thickness. Blocks are drawn
from a generator seeded by (seed, crater id), so a crater's blocks are the same whichever part of
the world asks for them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.craters.population import Craters
from sim.errors import SimError
from sim.rocks import sample_diameters


@dataclass(frozen=True)
class EjectaConfig:
    min_crater_diameter_m: float = 10.0  # smaller craters stay in the regolith: no blocks
    fresh_degradation: float = 0.3  # craters more degraded than this have shed or buried theirs
    largest_block_coeff: float = 0.29
    largest_block_exponent: float = 0.70
    cumulative_slope: float = 2.5
    min_block_m: float = 0.1
    max_block_m: float = 3.0
    inner_radius: float = 0.9
    outer_radius: float = 3.0
    density_scale: float = 1.0


@dataclass(frozen=True)
class EjectaBlocks:
    """Blocks: ``xy_m`` (M, 2) world positions, ``diameter_m`` (M,), ``crater_id`` (M,) of the crater
    that threw each."""

    xy_m: np.ndarray
    diameter_m: np.ndarray
    crater_id: np.ndarray

    def __len__(self) -> int:
        return len(self.diameter_m)


def blocky(craters: Craters, cfg: EjectaConfig = EjectaConfig()) -> np.ndarray:
    """Boolean (N,): the craters that carry ejecta blocks."""
    return (craters.diameter_m >= cfg.min_crater_diameter_m) & (craters.degradation < cfg.fresh_degradation)


def expected_blocks(diameter_m: np.ndarray, degradation: np.ndarray, cfg: EjectaConfig = EjectaConfig()) -> np.ndarray:
    """Expected number of blocks (N,) of craters of ``diameter_m`` and ``degradation`` (0 if not blocky)."""
    d = np.asarray(diameter_m, dtype=float)
    l_max = cfg.largest_block_coeff * d**cfg.largest_block_exponent
    l_hi = np.minimum(l_max, cfg.max_block_m)
    s = cfg.cumulative_slope
    n = (cfg.min_block_m / l_max) ** -s - (l_hi / l_max) ** -s + (l_hi >= l_max)
    n = np.where(l_hi > cfg.min_block_m, n, 0.0)
    keep = np.clip(1.0 - np.asarray(degradation) / cfg.fresh_degradation, 0.0, 1.0)
    ok = (d >= cfg.min_crater_diameter_m) & (np.asarray(degradation) < cfg.fresh_degradation)
    return np.where(ok, cfg.density_scale * n * keep, 0.0)


def ejecta_blocks(craters: Craters, seed: int, cfg: EjectaConfig = EjectaConfig()) -> EjectaBlocks:
    """The blocks of every blocky crater in ``craters`` (seeded per crater by (seed, crater id))."""
    if not 0 < cfg.inner_radius < cfg.outer_radius:
        raise SimError(f"ejecta radii must satisfy 0 < inner < outer, got {cfg.inner_radius}, {cfg.outer_radius}")
    lam = expected_blocks(craters.diameter_m, craters.degradation, cfg)
    xy, size, owner = [], [], []
    for k in np.flatnonzero(lam > 0):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xE1EC7A, int(craters.id[k]) & 0xFFFFFFFFFFFF])
        n = int(rng.poisson(lam[k]))
        if n == 0:
            continue
        d_crater = craters.diameter_m[k]
        l_max = cfg.largest_block_coeff * d_crater**cfg.largest_block_exponent
        l_hi = min(l_max, cfg.max_block_m)
        size.append(sample_diameters(n, cfg.min_block_m, l_hi, cfg.cumulative_slope, rng))
        # density ~ rho^-3 on the plane: pdf(rho) ~ rho^-2, inverse CDF
        a, b = 1.0 / cfg.inner_radius, 1.0 / cfg.outer_radius
        rho = 1.0 / (a - rng.random(n) * (a - b))
        th = rng.uniform(0.0, 2.0 * np.pi, n)
        r = rho * 0.5 * d_crater
        xy.append(craters.xy_m[k] + np.column_stack([r * np.cos(th), r * np.sin(th)]))
        owner.append(np.full(n, craters.id[k], dtype=np.int64))
    if not size:
        return EjectaBlocks(np.zeros((0, 2)), np.zeros(0), np.zeros(0, dtype=np.int64))
    return EjectaBlocks(np.vstack(xy), np.concatenate(size), np.concatenate(owner))

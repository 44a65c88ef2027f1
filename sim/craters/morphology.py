"""Crater morphology: radial height profiles of simple craters, fresh to degraded, stamped onto
heightmaps (additively: overlapping craters superpose).

Fresh simple crater (units of the rim diameter D, radius R = D / 2, rho = r / R):
- bowl, rho <= 1: z = h_rim - d + d rho^2 with depth (rim crest to floor) d = 0.2 D (Pike 1977,
  Garvin et al. 2003 for Mars: d/D ~ 0.2 for fresh simple craters) and rim height h_rim = 0.04 D
  (Pike 1977: h_rim ~ 0.036-0.04 D); the wall at the rim is ~39 deg;
- rim flank and ejecta blanket, 1 < rho <= 3: z = h_rim (rho^-3 - 3^-3) / (1 - 3^-3) (ejecta
  thickness ~ (r/R)^-3, McGetchin et al. 1973), zero beyond.

Degradation ``g`` in [0, 1] (0 fresh, 1 nearly erased) acts as infilling and diffusion (the two
processes Fassett & Thomson 2014 and Mars' aeolian record describe): the floor is filled up to
0.7 g of its depth below the surroundings, then the profile is smoothed (Gaussian, sigma = 0.3 g R),
so depth and rim height both shrink and the rim crest rounds off. Profiles are tabulated on
rho in [0, INFLUENCE_RADIUS] for DEGRADATION_LEVELS quantised degradations (:func:`quantise`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter1d

from sim.errors import SimError

FRESH_DEPTH_RATIO = 0.20
FRESH_RIM_RATIO = 0.04
EJECTA_RADIUS = 3.0  # rho where the ejecta blanket ends
INFLUENCE_RADIUS = 4.0  # rho beyond which a crater changes nothing (smoothing tail tapered off)
INFILL_FRACTION = 0.7
DIFFUSION_SIGMA = 0.3  # sigma / R at full degradation
DEGRADATION_LEVELS = 64
_D_RHO = 1.0 / 256.0
_RHO = np.arange(0.0, INFLUENCE_RADIUS + 0.5 * _D_RHO, _D_RHO)


def quantise(degradation) -> np.ndarray:
    """Degradation rounded to the tabulated levels (multiples of 1 / DEGRADATION_LEVELS in [0, 1])."""
    g = np.asarray(degradation, dtype=float)
    if not np.all(np.isfinite(g)):
        raise SimError("crater degradation contains NaN or inf")
    return np.round(np.clip(g, 0.0, 1.0) * DEGRADATION_LEVELS) / DEGRADATION_LEVELS


def fresh_profile(rho: np.ndarray) -> np.ndarray:
    """Height / D of a fresh crater at ``rho`` = r / R (array)."""
    rho = np.asarray(rho, dtype=float)
    d, h = FRESH_DEPTH_RATIO, FRESH_RIM_RATIO
    inside = h - d + d * rho**2
    e = EJECTA_RADIUS**-3.0
    outside = h * (np.maximum(rho, 1.0) ** -3.0 - e) / (1.0 - e)
    return np.where(rho <= 1.0, inside, np.where(rho <= EJECTA_RADIUS, outside, 0.0))


@lru_cache(maxsize=DEGRADATION_LEVELS + 1)
def _profile_level(level: int) -> np.ndarray:
    g = level / DEGRADATION_LEVELS
    f = fresh_profile(_RHO)
    floor = FRESH_RIM_RATIO - FRESH_DEPTH_RATIO
    fill = floor * (1.0 - INFILL_FRACTION * g)
    f = np.where(_RHO < 1.0, np.maximum(f, fill), f)
    sigma = DIFFUSION_SIGMA * g / _D_RHO
    if sigma > 0:
        sym = np.concatenate([f[:0:-1], f])  # f(|x|) on x in [-4, 4]
        f = gaussian_filter1d(sym, sigma, mode="nearest")[len(f) - 1:]
    taper = np.clip((INFLUENCE_RADIUS - _RHO) / 0.5, 0.0, 1.0)  # to exactly 0 at the influence radius
    f = f * taper
    f.setflags(write=False)
    return f


@lru_cache(maxsize=1)
def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Profiles (levels, rho) and per level the depth / D and the rim height / D."""
    prof = np.stack([_profile_level(k) for k in range(DEGRADATION_LEVELS + 1)])
    prof.setflags(write=False)
    return prof, prof.max(axis=1) - prof[:, 0], prof.max(axis=1)


def _levels(degradation) -> np.ndarray:
    return np.rint(quantise(degradation) * DEGRADATION_LEVELS).astype(int)


def _profile_of_level(rho: np.ndarray, level: int) -> np.ndarray:
    """Linear interpolation in the uniform rho table (0 beyond it; faster than np.interp)."""
    table = _tables()[0][level]
    f = np.minimum(np.asarray(rho, dtype=float) * (1.0 / _D_RHO), len(table) - 1.0)
    i = f.astype(np.intp)
    f -= i
    j = np.minimum(i + 1, len(table) - 1)
    return table[i] * (1.0 - f) + table[j] * f


def profile(rho: np.ndarray, degradation: float) -> np.ndarray:
    """Height / D at ``rho`` = r / R of a crater of ``degradation`` (quantised)."""
    return _profile_of_level(rho, int(_levels(degradation)))


def depth_ratio(degradation) -> np.ndarray:
    """Depth (rim crest to centre) / D for ``degradation`` (array, quantised)."""
    return _tables()[1][_levels(degradation)]


def rim_ratio(degradation) -> np.ndarray:
    """Rim crest height above the surroundings / D for ``degradation`` (array, quantised)."""
    return _tables()[2][_levels(degradation)]


def crater_relief(xy_m: np.ndarray, centres_m: np.ndarray, diameters_m: np.ndarray, degradation: np.ndarray) -> np.ndarray:
    """Height change (N,) at world points ``xy_m`` (N, 2) from craters (centres (C, 2), rim
    diameters (C,), degradation (C,)), summed."""
    xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
    out = np.zeros(len(xy))
    levels = _levels(np.ravel(degradation)).tolist()
    for c, d, lv in zip(np.reshape(centres_m, (-1, 2)), np.ravel(diameters_m).tolist(), levels):
        rho = np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1]) / (0.5 * d)
        near = rho < INFLUENCE_RADIUS
        if np.any(near):
            out[near] += d * _profile_of_level(rho[near], lv)
    return out


def stamp_relief(z_m: np.ndarray, extent: tuple[float, float, float, float], centres_m: np.ndarray,
                 diameters_m: np.ndarray, degradation: np.ndarray) -> np.ndarray:
    """``z_m`` (ny, nx) grid heights (row i at y = ymin + i dy, column j at x = xmin + j dx, the
    :class:`sim.terrain.Heightmap` convention) plus the craters' relief; a new array."""
    z = np.array(z_m, dtype=float)
    ny, nx = z.shape
    xmin, xmax, ymin, ymax = extent
    dx, dy = (xmax - xmin) / (nx - 1), (ymax - ymin) / (ny - 1)
    levels = _levels(np.ravel(degradation)).tolist()
    for (cx, cy), d, lv in zip(np.reshape(centres_m, (-1, 2)).tolist(), np.ravel(diameters_m).tolist(), levels):
        c = (cx, cy)
        reach = INFLUENCE_RADIUS * 0.5 * d
        j0, j1 = max(int(np.ceil((c[0] - reach - xmin) / dx)), 0), min(int(np.floor((c[0] + reach - xmin) / dx)), nx - 1)
        i0, i1 = max(int(np.ceil((c[1] - reach - ymin) / dy)), 0), min(int(np.floor((c[1] + reach - ymin) / dy)), ny - 1)
        if j1 < j0 or i1 < i0:
            continue
        gx = xmin + dx * np.arange(j0, j1 + 1) - c[0]
        gy = ymin + dy * np.arange(i0, i1 + 1) - c[1]
        rho = np.sqrt(gy[:, None] ** 2 + gx[None, :] ** 2) * (2.0 / d)
        z[i0:i1 + 1, j0:j1 + 1] += d * _profile_of_level(rho, lv)
    return z

"""Crater size-frequency: the Hartmann (2005) Mars production function scaled by age, capped by
Hartmann's (1984) empirical saturation equilibrium.

Production. Hartmann's isochrons give, for a surface of age T, the number of craters per km^2 in
root-2 diameter bins (bin i spans [D_i, sqrt(2) D_i), D_i = 2^((i - i_1km) / 2) km). The table
below is the 1 Gyr isochron of Hartmann (2005), "Martian cratering 8: Isochron refinement and the
chronology of Mars", Icarus 174, 294-320, as tabulated (typos corrected) by Michael (2013), Icarus
226, 885-890, Table 1, and used by craterstats ("Mars, Hartmann 2004 iteration"). Its small-crater
end (3.9-16 m) is flattened by the Martian atmosphere. Below its first bin (3.9 m) the first
bins' slope is extended (Hartmann & Daubar 2016 count more metre-scale craters: the
``hartmann_daubar2016`` table, from 0.98 m, is available as an option). The age scaling is the
Hartmann (2005) chronology in Michael's (2013, eq. 3) form:

    N(T) = N(1 Gyr) * f(T) / f(1),   f(T) = 3.79e-14 (exp(6.93 T) - 1) + 5.84e-4 T   (T in Gyr).

Equilibrium. Old surfaces do not keep every small crater: new ones erase old ones, and the count
saturates at Hartmann's (1984, Icarus 60, 56-74) empirical equilibrium, cumulative

    N_eq(>D) = 10^-1.14 D^-1.83   per km^2 (D in km),

which per root-2 bin is N_eq(>D) (1 - 2^(-1.83/2)). The model density per bin is
min(production(T), equilibrium). Within a bin, diameters follow the power law through the
neighbouring bins' densities.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from sim.errors import SimError

# 1 Gyr isochrons, craters per km^2 per root-2 bin; bin i starts at 2^((i - i_1km) / 2) km.
HARTMANN_2005 = (16, (
    4.04e3, 2.33e3, 1.14e3, 4.58e2, 1.91e2, 6.66e1, 2.40e1, 9.44e0, 3.30e0, 1.22e0, 4.37e-1,
    1.47e-1, 4.70e-2, 1.38e-2, 4.02e-3, 1.15e-3, 3.08e-4, 1.28e-4, 6.85e-5, 3.67e-5, 1.98e-5,
    1.06e-5, 5.68e-6, 3.04e-6, 1.62e-6, 8.71e-7, 4.67e-7, 2.40e-7, 1.12e-7, 5.21e-8, 2.43e-8,
))
HARTMANN_DAUBAR_2016 = (20, (
    1.10e5, 7.50e4, 4.50e4, 2.40e4, 1.10e4, 4.20e3, 1.60e3, 6.00e2, 1.90e2, 6.70e1, 2.40e1,
    9.44e0, 3.30e0, 1.22e0, 4.37e-1, 1.47e-1, 4.70e-2, 1.38e-2, 4.02e-3, 1.15e-3, 3.08e-4,
))
PRODUCTION_TABLES = {"hartmann2005": HARTMANN_2005, "hartmann_daubar2016": HARTMANN_DAUBAR_2016}
EQUILIBRIUM_LOG10_A = -1.14  # Hartmann (1984), cumulative, per km^2, D in km
EQUILIBRIUM_SLOPE = -1.83
KM2_PER_M2 = 1e-6


def hartmann_age_scale(age_gyr: float) -> float:
    """N(T) / N(1 Gyr) of the Hartmann (2005) chronology (Michael 2013, eq. 3)."""
    def f(t: float) -> float:
        return 3.79e-14 * (np.exp(6.93 * t) - 1.0) + 5.84e-4 * t

    return float(f(age_gyr) / f(1.0))


@dataclass(frozen=True)
class CraterSFD:
    """Crater population of a surface of ``age_gyr``: production (``production`` table name) times
    the age scale, capped per bin by the equilibrium when ``equilibrium``; diameters in
    [``d_min_m``, ``d_max_m``]. ``density_scale`` multiplies the whole population (1: the model)."""

    age_gyr: float = 1.0
    production: str = "hartmann2005"
    equilibrium: bool = True
    d_min_m: float = 1.0
    d_max_m: float = 200.0
    density_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.production not in PRODUCTION_TABLES:
            raise SimError(f"crater production must be one of {sorted(PRODUCTION_TABLES)}, got {self.production!r}")
        if not (np.isfinite(self.age_gyr) and 0.0 < self.age_gyr <= 4.5):
            raise SimError(f"crater age_gyr must be in (0, 4.5], got {self.age_gyr}")
        if not (0.0 < self.d_min_m < self.d_max_m <= 2000.0):
            raise SimError(f"crater diameters need 0 < d_min_m < d_max_m <= 2000, got {self.d_min_m}, {self.d_max_m}")
        if not (np.isfinite(self.density_scale) and self.density_scale >= 0.0):
            raise SimError(f"crater density_scale must be >= 0, got {self.density_scale}")

    # -- bins ------------------------------------------------------------------------------
    @cached_property
    def _bins(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bin lower edges (m), production and equilibrium densities per m^2 per bin, covering
        [d_min_m, d_max_m] (the table's end slopes extended beyond it)."""
        i1, table = PRODUCTION_TABLES[self.production]
        h = np.asarray(table, dtype=float) * hartmann_age_scale(self.age_gyr)
        lo_i = int(np.floor(2.0 * np.log2(self.d_min_m / 1000.0))) + i1
        hi_i = int(np.ceil(2.0 * np.log2(self.d_max_m / 1000.0))) + i1
        idx = np.arange(lo_i, hi_i + 1)
        log_h = np.log(h)
        first, last = log_h[1] - log_h[0], log_h[-1] - log_h[-2]
        k = np.clip(idx, 0, len(h) - 1)
        log_p = log_h[k] + np.where(idx < 0, idx * first, 0.0) + np.where(idx >= len(h), (idx - len(h) + 1) * last, 0.0)
        d_lo_m = 1000.0 * 2.0 ** ((idx - i1) / 2.0)
        eq_cum = 10.0**EQUILIBRIUM_LOG10_A * (d_lo_m / 1000.0) ** EQUILIBRIUM_SLOPE
        eq_bin = eq_cum * (1.0 - 2.0 ** (EQUILIBRIUM_SLOPE / 2.0))
        return d_lo_m, np.exp(log_p) * KM2_PER_M2, eq_bin * KM2_PER_M2

    def bin_density_per_m2(self, d_lo_m: np.ndarray) -> np.ndarray:
        """Model craters per m^2 in the root-2 bins starting at ``d_lo_m`` (interpolated in log-log)."""
        lo, prod, eq = self._bins
        dens = np.minimum(prod, eq) if self.equilibrium else prod
        return self.density_scale * np.exp(np.interp(np.log(d_lo_m), np.log(lo), np.log(dens)))

    def saturation_ratio(self, d_m: np.ndarray) -> np.ndarray:
        """Production / equilibrium density at ``d_m`` (> 1: the surface is saturated there)."""
        lo, prod, eq = self._bins
        return np.exp(np.interp(np.log(d_m), np.log(lo), np.log(prod / eq)))

    def _differential(self, d_m: np.ndarray) -> np.ndarray:
        """dN/dD per m^2 per m: a bin's count over its width, as a smooth power law."""
        return self.bin_density_per_m2(d_m / 2**0.25) / (d_m / 2**0.25 * (2**0.5 - 1.0))

    @cached_property
    def _cdf_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Cumulative N(>D) per m^2 on a fine log grid over [d_min_m, d_max_m]."""
        d = np.geomspace(self.d_min_m, self.d_max_m, 2049)
        f = self._differential(d)
        seg = 0.5 * (f[1:] + f[:-1]) * np.diff(d)  # trapezoid in D
        above = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
        return d, above

    def cumulative_per_m2(self, d_m) -> np.ndarray:
        """Model N(>D) per m^2 for diameters ``d_m`` within [d_min_m, d_max_m] (craters up to d_max_m)."""
        d, above = self._cdf_grid
        return np.interp(np.log(np.asarray(d_m, dtype=float)), np.log(d), above)

    def expected_count(self, area_m2: float, d_lo_m: float | None = None, d_hi_m: float | None = None) -> float:
        """Expected number of craters with d_lo_m <= D < d_hi_m (default: the whole range) on ``area_m2``."""
        lo = self.d_min_m if d_lo_m is None else max(d_lo_m, self.d_min_m)
        hi = self.d_max_m if d_hi_m is None else min(d_hi_m, self.d_max_m)
        if hi <= lo:
            return 0.0
        return float(area_m2 * (self.cumulative_per_m2(lo) - self.cumulative_per_m2(hi)))

    def sample_diameters(self, n: int, rng: np.random.Generator, d_lo_m: float | None = None,
                         d_hi_m: float | None = None) -> np.ndarray:
        """``n`` diameters (m) drawn from the model in [d_lo_m, d_hi_m) (inverse of N(>D))."""
        d, above = self._cdf_grid
        lo = self.d_min_m if d_lo_m is None else max(d_lo_m, self.d_min_m)
        hi = self.d_max_m if d_hi_m is None else min(d_hi_m, self.d_max_m)
        a_lo, a_hi = self.cumulative_per_m2(lo), self.cumulative_per_m2(hi)
        u = a_hi + (a_lo - a_hi) * rng.random(n)
        # above decreases with d: interpolate log D against the reversed cumulative
        return np.exp(np.interp(u, above[::-1], np.log(d)[::-1]))

"""Rock size-frequency of Mars landing sites: Golombek & Rapp (1997).

The cumulative fractional area covered by rocks of diameter >= D is

    F_k(D) = k exp(-q(k) D),   q(k) = 1.79 + 0.152 / k,

with k the total rock abundance (k ~ 2-20 % at landing sites: Viking Lander 2 ~ 15-20 %, typical
plains 5-8 %). Counting a rock of diameter D as a disc of area pi D^2 / 4, the number of rocks per
m^2 per metre of diameter is n(D) = -dF/dD / (pi D^2 / 4) = k q exp(-q D) 4 / (pi D^2); the
model is truncated to [d_min_m, d_max_m].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from sim.errors import SimError


@dataclass(frozen=True)
class GolombekRapp:
    """Rock population of abundance ``k`` (fraction of area covered by all rocks), diameters in
    [``d_min_m``, ``d_max_m``]."""

    k: float
    d_min_m: float = 0.1
    d_max_m: float = 3.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.k) and 0.0 < self.k < 1.0):
            raise SimError(f"rock abundance k must be in (0, 1), got {self.k}")
        if not 0.0 < self.d_min_m < self.d_max_m:
            raise SimError(f"rock diameters need 0 < d_min_m < d_max_m, got {self.d_min_m}, {self.d_max_m}")

    @property
    def q(self) -> float:
        return 1.79 + 0.152 / self.k

    def cumulative_area(self, d_m) -> np.ndarray:
        """F_k(D): fraction of the area covered by rocks of diameter >= ``d_m`` (untruncated model)."""
        return self.k * np.exp(-self.q * np.asarray(d_m, dtype=float))

    def differential_number(self, d_m) -> np.ndarray:
        """Rocks per m^2 per m of diameter at ``d_m``."""
        d = np.asarray(d_m, dtype=float)
        return self.k * self.q * np.exp(-self.q * d) * 4.0 / (np.pi * d * d)

    @cached_property
    def _table(self) -> tuple[np.ndarray, np.ndarray]:
        d = np.geomspace(self.d_min_m, self.d_max_m, 4097)
        f = self.differential_number(d)
        seg = 0.5 * (f[1:] + f[:-1]) * np.diff(d)
        return d, np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])

    def cumulative_number(self, d_m) -> np.ndarray:
        """Rocks per m^2 with diameter >= ``d_m`` (up to d_max_m)."""
        d, above = self._table
        return np.interp(np.log(np.clip(np.asarray(d_m, dtype=float), self.d_min_m, self.d_max_m)), np.log(d), above)

    @property
    def density_per_m2(self) -> float:
        """All rocks of the model per m^2."""
        return float(self.cumulative_number(self.d_min_m))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` diameters (m) from the model (inverse of the cumulative number)."""
        d, above = self._table
        u = rng.random(n) * above[0]
        return np.exp(np.interp(u, above[::-1], np.log(d)[::-1]))

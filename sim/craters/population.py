"""Crater tables and seeded crater populations of a region."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.craters.morphology import depth_ratio, quantise, rim_ratio
from sim.craters.sfd import CraterSFD
from sim.errors import SimError


@dataclass(frozen=True)
class Craters:
    """Craters in the world frame: ``xy_m`` (N, 2) centres, ``diameter_m`` (N,) rim diameters,
    ``degradation`` (N,) in [0, 1] (0 fresh; quantised, see :func:`sim.craters.quantise`) and
    ``id`` (N,) int64 stable identities. Depth and rim height follow from the morphology."""

    xy_m: np.ndarray
    diameter_m: np.ndarray
    degradation: np.ndarray
    id: np.ndarray

    def __post_init__(self) -> None:
        xy = np.reshape(np.asarray(self.xy_m, dtype=float), (-1, 2))
        n = len(xy)
        d = np.reshape(np.asarray(self.diameter_m, dtype=float), (-1,))
        g = np.reshape(np.asarray(self.degradation, dtype=float), (-1,))
        ids = np.reshape(np.asarray(self.id, dtype=np.int64), (-1,))
        if not (len(d) == len(g) == len(ids) == n):
            raise SimError(f"Craters: xy_m {xy.shape}, diameter_m {d.shape}, degradation {g.shape}, id {ids.shape} disagree")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(d))):
            raise SimError("Craters: xy_m or diameter_m contains NaN or inf")
        if np.any(d <= 0):
            raise SimError("Craters: diameter_m must be positive")
        for name, value in (("xy_m", xy), ("diameter_m", d), ("degradation", quantise(g)), ("id", ids)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.xy_m.shape[0])

    @property
    def depth_m(self) -> np.ndarray:
        """Rim crest to floor depth (N,) m."""
        return depth_ratio(self.degradation) * self.diameter_m

    @property
    def rim_height_m(self) -> np.ndarray:
        """Rim crest above the surrounding surface (N,) m."""
        return rim_ratio(self.degradation) * self.diameter_m

    @staticmethod
    def empty() -> Craters:
        return Craters(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))

    @staticmethod
    def concat(parts: list[Craters]) -> Craters:
        if not parts:
            return Craters.empty()
        return Craters(np.vstack([p.xy_m for p in parts]), np.concatenate([p.diameter_m for p in parts]),
                       np.concatenate([p.degradation for p in parts]), np.concatenate([p.id for p in parts]))

    def subset(self, keep) -> Craters:
        """The craters selected by boolean or index array ``keep``."""
        return Craters(self.xy_m[keep], self.diameter_m[keep], self.degradation[keep], self.id[keep])

    def reaching(self, extent: tuple[float, float, float, float], reach_radii: float) -> Craters:
        """Craters whose disc of ``reach_radii`` crater radii meets the box ``extent``."""
        xmin, xmax, ymin, ymax = extent
        r = reach_radii * 0.5 * self.diameter_m
        dx = np.maximum(np.maximum(xmin - self.xy_m[:, 0], self.xy_m[:, 0] - xmax), 0.0)
        dy = np.maximum(np.maximum(ymin - self.xy_m[:, 1], self.xy_m[:, 1] - ymax), 0.0)
        return self.subset(dx * dx + dy * dy <= r * r)


def sample_degradation(sfd: CraterSFD, diameter_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Degradation of craters of ``diameter_m``: the age of a surviving crater is uniform over its
    lifetime, and a crater is fully degraded at the end of it. Where the surface is saturated
    (production above equilibrium) craters live shorter than the surface and their degradation
    is uniform in [0, 1]; elsewhere the oldest is only as degraded as the surface's age over the
    crater's lifetime, the production / equilibrium ratio: g = U(0, 1) min(1, ratio)."""
    return quantise(rng.random(len(diameter_m)) * np.minimum(1.0, sfd.saturation_ratio(diameter_m)))


def sample_craters(sfd: CraterSFD, extent: tuple[float, float, float, float], rng: np.random.Generator,
                   *, d_lo_m: float | None = None, d_hi_m: float | None = None, id_base: int = 0) -> Craters:
    """A seeded population of ``sfd`` with centres uniform in ``extent`` (xmin, xmax, ymin, ymax),
    diameters in [d_lo_m, d_hi_m) (default the model's range); ids ``id_base + k``."""
    xmin, xmax, ymin, ymax = extent
    if not (xmax > xmin and ymax > ymin):
        raise SimError(f"sample_craters: empty extent {extent}")
    n = int(rng.poisson(sfd.expected_count((xmax - xmin) * (ymax - ymin), d_lo_m, d_hi_m)))
    d = sfd.sample_diameters(n, rng, d_lo_m, d_hi_m)
    xy = np.column_stack([rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)])
    g = sample_degradation(sfd, d, rng)
    return Craters(xy, d, g, id_base + np.arange(n, dtype=np.int64))

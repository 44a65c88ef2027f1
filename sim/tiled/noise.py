"""Seamless procedural terrain: fractal value noise on hashed lattices.

Each octave is a lattice of spacing s whose node values come from a 64-bit integer hash of
(seed, octave, i, j) (splitmix64 finaliser), interpolated with the quintic fade 6t^5 - 15t^4 + 10t^3
(C2: smooth slopes and normals). A height is a pure function of the world position, so any tile,
any point and any generation order give the same value, and neighbouring tiles meet without
seams. Octave amplitudes follow a Hurst exponent: a_k = relief (s_k / s_0)^H.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_PRIME_J = np.uint64(0xC2B2AE3D27D4EB4F)


def hash_uniform(seed: int, octave: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Uniform values in [-1, 1) for integer lattice indices ``i``, ``j`` (broadcast), from a
    splitmix64-style hash of (seed, octave, i, j)."""
    with np.errstate(over="ignore"):
        key = np.uint64((int(seed) * 0x2545F4914F6CDD1D + int(octave) * 0x632BE59BD9B4E019) & 0xFFFFFFFFFFFFFFFF)
        h = (np.asarray(i, dtype=np.int64).astype(np.uint64) * _GOLD) ^ (
            np.asarray(j, dtype=np.int64).astype(np.uint64) * _PRIME_J) ^ key
        h = (h ^ (h >> np.uint64(30))) * _M1
        h = (h ^ (h >> np.uint64(27))) * _M2
        h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) * (2.0 / 2.0**53) - 1.0


def _fade(t: np.ndarray) -> np.ndarray:
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@dataclass(frozen=True)
class FractalNoise:
    """Sum of value-noise octaves of spacings ``largest_m``, ``largest_m`` / 2, ... down to
    ``smallest_m``; amplitudes ``relief_m`` (s / largest_m)^``hurst``."""

    seed: int
    relief_m: float
    largest_m: float = 512.0
    smallest_m: float = 1.0
    hurst: float = 0.8

    def octaves(self, min_spacing_m: float = 0.0, max_spacing_m: float = np.inf) -> list[tuple[int, float, float]]:
        """(index, spacing m, amplitude m) of the octaves with spacing in [min, max]."""
        out = []
        s, k = self.largest_m, 0
        while s >= self.smallest_m * (1 - 1e-9):
            if min_spacing_m <= s <= max_spacing_m:
                out.append((k, s, self.relief_m * (s / self.largest_m) ** self.hurst))
            s, k = s / 2.0, k + 1
        return out

    def grid(self, x_m: np.ndarray, y_m: np.ndarray, *, min_spacing_m: float = 0.0,
             max_spacing_m: float = np.inf) -> np.ndarray:
        """Heights (len(y), len(x)) on the grid of coordinates ``x_m`` (columns) and ``y_m`` (rows)."""
        x = np.asarray(x_m, dtype=float)
        y = np.asarray(y_m, dtype=float)
        z = np.zeros((len(y), len(x)))
        for k, s, amp in self.octaves(min_spacing_m, max_spacing_m):
            fx, fy = x / s, y / s
            ix, iy = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
            wx, wy = _fade(fx - ix), _fade(fy - iy)
            jx0, jy0 = int(ix.min()), int(iy.min())
            lat = hash_uniform(self.seed, k, np.arange(jy0, int(iy.max()) + 2)[:, None],
                               np.arange(jx0, int(ix.max()) + 2)[None, :])
            cx, cy = ix - jx0, iy - jy0
            along_x = lat[:, cx] * (1.0 - wx) + lat[:, cx + 1] * wx  # (lattice rows, len(x))
            z += amp * (along_x[cy] * (1.0 - wy)[:, None] + along_x[cy + 1] * wy[:, None])
        return z

    def at(self, xy_m: np.ndarray, *, min_spacing_m: float = 0.0, max_spacing_m: float = np.inf) -> np.ndarray:
        """Heights (N,) at scattered world points ``xy_m`` (N, 2)."""
        xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
        z = np.zeros(len(xy))
        for k, s, amp in self.octaves(min_spacing_m, max_spacing_m):
            f = xy / s
            i = np.floor(f).astype(np.int64)
            w = _fade(f - i)
            v00 = hash_uniform(self.seed, k, i[:, 1], i[:, 0])
            v01 = hash_uniform(self.seed, k, i[:, 1], i[:, 0] + 1)
            v10 = hash_uniform(self.seed, k, i[:, 1] + 1, i[:, 0])
            v11 = hash_uniform(self.seed, k, i[:, 1] + 1, i[:, 0] + 1)
            a = v00 * (1 - w[:, 0]) + v01 * w[:, 0]
            b = v10 * (1 - w[:, 0]) + v11 * w[:, 0]
            z += amp * (a * (1 - w[:, 1]) + b * w[:, 1])
        return z

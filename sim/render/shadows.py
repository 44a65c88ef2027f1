"""Cast shadows: a point is sunlit when its ray towards the sun leaves the scene unblocked.

Shadow rays are cast only for sun-facing hits, and in a camera view only where the image needs
them: first on the "black" pixels of a checkerboard; a "white" pixel takes the flag of its four
black neighbours (up, down, left, right) when they all agree and lie on the same surface as the
pixel (same rock id, inverse depth the mean of theirs within a tolerance, as it is on a plane);
every other sun-facing pixel gets its own ray. Only a shadow that covers a white pixel and none
of its four neighbours (one isolated pixel, or a one-pixel diagonal line) can be missed: 12 of
9.2 M pixels on the 40 held-out views of ``fgslam bench detect`` (docs/detectors.md), for about
half the shadow rays. The
right view of a rectified pair takes the left view's flag where it sees the same surface point
(:func:`right_from_left`).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np

from sim.world import RaycastScene, RayHits

SHADOW_OFFSET_M = 0.01  # shadow rays start this far off the surface, along its normal
INV_DEPTH_TOL = 0.02  # relative: a sample pair whose mean inverse depth is off by more spans an edge


class SunTest:
    """Shadow rays for the first hits ``hits`` of ``rays`` (N, 6) float32 towards the unit ``sun``
    (3,) float32: ``sunlit(idx)`` for hit indices into the N rays."""

    def __init__(self, scene: RaycastScene, rays: np.ndarray, hits: RayHits, sun: np.ndarray, nthreads: int = 0) -> None:
        self._scene, self._rays, self._hits, self._sun, self._nthreads = scene, rays, hits, sun, nthreads
        # above the highest vertex nothing can block the sun: stop the ray there
        self._t_far_m = (scene.z_top_m - scene.z_bottom_m + 0.1) / max(float(sun[2]), 1e-3)
        self.n_rays = 0  # shadow rays cast so far

    def sunlit(self, idx: np.ndarray) -> np.ndarray:
        """Boolean (K,): the hits ``idx`` (K,) whose ray towards the sun is not blocked."""
        if len(idx) == 0:
            return np.zeros(0, dtype=bool)
        r = np.take(self._rays, idx, axis=0)
        t = self._hits.t_m[idx]
        normal = np.take(self._hits.normal, idx, axis=0)
        for c in range(3):
            p = r[:, 3 + c] * t
            p += r[:, c]
            np.multiply(normal[:, c], np.float32(SHADOW_OFFSET_M), out=r[:, c])
            r[:, c] += p
            r[:, 3 + c] = self._sun[c]
        self.n_rays += len(idx)
        return self._scene.unoccluded(r, self._t_far_m, self._nthreads)


@lru_cache(maxsize=4)
def _checkerboard(h: int, w: int) -> np.ndarray:
    """Boolean (h, w): pixels whose row + column is even (read-only)."""
    board = (np.add.outer(np.arange(h), np.arange(w)) % 2) == 0
    board.setflags(write=False)
    return board


def sampled_sunlit(sunlit: Callable[[np.ndarray], np.ndarray], facing: np.ndarray, instance: np.ndarray,
                   inv_depth: np.ndarray, tol: float = INV_DEPTH_TOL) -> np.ndarray:
    """Sun flags (H*W,) of one view's pixels from ``sunlit(pixel indices)`` on the checkerboard
    plus the pixels it cannot settle (module doc); ``facing`` (H, W) sun-facing hits,
    ``instance`` (H, W) rock rows, ``inv_depth`` (H, W) 1 / optical depth (1 / m)."""
    H, W = facing.shape
    sample = facing & _checkerboard(H, W)
    lit = np.zeros((H, W), dtype=bool)
    idx = np.flatnonzero(sample)
    lit.ravel()[idx] = sunlit(idx)
    done = sample.copy()
    if H > 2 and W > 2:
        inner = np.s_[1:-1, 1:-1]
        around = (np.s_[:-2, 1:-1], np.s_[2:, 1:-1], np.s_[1:-1, :-2], np.s_[1:-1, 2:])  # up, down, left, right
        inst, q = instance[inner], inv_depth[inner]
        ok = facing[inner] & ~sample[inner]
        flag = lit[around[0]]
        q_mean = np.zeros_like(q)
        for s in around:
            ok &= sample[s] & (instance[s] == inst) & (lit[s] == flag)
            q_mean += inv_depth[s]
        q_mean *= np.float32(0.25)
        ok &= np.abs(q_mean - q) <= np.float32(tol) * q
        lit[inner] |= ok & flag
        done[inner] |= ok
    rest = np.flatnonzero(facing & ~done)
    lit.ravel()[rest] = sunlit(rest)
    return lit.ravel()


def right_from_left(lit_left: np.ndarray, depth_left_m: np.ndarray, facing_right: np.ndarray, z_right_m: np.ndarray,
                    col: np.ndarray, disparity_px_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Sun flags of a rectified right view taken from the left view: (flags (N,), pixel indices
    (K,) still to test). A right-view hit at pixel (row, col) and optical depth z lies in the left
    view at column col + 0.5 + f b / z of the same row (``disparity_px_m`` = f b); where the left
    view sees the same surface there (depth within 1 cm + 1 %) and the flag does not change across
    that pixel's row neighbours (the point is within half a pixel of the left hit), it takes the
    left view's flag. ``lit_left`` (H, W), ``depth_left_m``, ``facing_right``, ``z_right_m``,
    ``col`` (N = H W,) row-major."""
    H, W = lit_left.shape
    steady = np.ones((H, W), dtype=bool)
    steady[:, 1:] = lit_left[:, 1:] == lit_left[:, :-1]
    steady[:, :-1] &= steady[:, 1:].copy()
    n = len(facing_right)
    u = np.floor(col + np.float32(0.5) + np.float32(disparity_px_m) / z_right_m)  # float64; z inf on a miss
    ok = facing_right & (u < W)
    left_pix = np.where(ok, np.arange(n) - col + u.astype(np.intp), 0)
    with np.errstate(invalid="ignore"):  # inf - inf where neither view hits: not facing anyway
        same = np.abs(depth_left_m[left_pix] - z_right_m) < 0.01 + 0.01 * z_right_m
    same &= ok
    same &= steady.ravel()[left_pix]
    return same & lit_left.ravel()[left_pix], np.flatnonzero(facing_right & ~same)

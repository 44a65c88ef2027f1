"""Rectified pinhole camera: pixel grid, unit ray directions in the optical frame (z forward,
x right, y down; pixel (u, v) = (f x / z + cx, f y / z + cy), pixel centres at integers + 0.5)
and world rays from a camera pose."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from sim.render.config import RenderError


@dataclass(frozen=True)
class PinholeCamera:
    """Rectified pinhole camera: image size, focal length and principal point in pixels."""

    width_px: int
    height_px: int
    f_px: float
    cx_px: float
    cy_px: float

    @staticmethod
    def from_fov(width_px: int, height_px: int, hfov_deg: float) -> PinholeCamera:
        """Camera with horizontal field of view ``hfov_deg`` and a centred principal point."""
        if width_px < 1 or height_px < 1 or not 0 < hfov_deg < 170:
            raise RenderError(f"bad camera: {width_px} x {height_px} px, hfov {hfov_deg} deg")
        f = 0.5 * width_px / np.tan(np.deg2rad(hfov_deg) / 2)
        return PinholeCamera(int(width_px), int(height_px), float(f), width_px / 2.0, height_px / 2.0)

    def ray_dirs_cam(self) -> np.ndarray:
        """Unit ray directions (H*W, 3) through the pixel centres, optical frame, row-major."""
        u = np.arange(self.width_px) + 0.5
        v = np.arange(self.height_px) + 0.5
        gu, gv = np.meshgrid(u, v)
        d = np.stack([(gu - self.cx_px) / self.f_px, (gv - self.cy_px) / self.f_px, np.ones_like(gu)], axis=-1)
        d = d.reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, xyz_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) (u, v) of optical-frame points ``xyz_cam`` (N, 3) (z > 0)."""
        p = np.reshape(xyz_cam, (-1, 3))
        return np.column_stack([self.f_px * p[:, 0] / p[:, 2] + self.cx_px, self.f_px * p[:, 1] / p[:, 2] + self.cy_px])


@dataclass(frozen=True)
class PixelGrid:
    """Per-pixel constants of a camera (row-major, read-only): ``dirs_cam`` (H*W, 3) float32 unit
    ray directions, ``z_cam`` (H*W,) float32 their optical z, ``col`` (H*W,) int64 pixel column."""

    dirs_cam: np.ndarray
    z_cam: np.ndarray
    col: np.ndarray


@lru_cache(maxsize=8)
def pixel_grid(camera: PinholeCamera) -> PixelGrid:
    """The (cached) :class:`PixelGrid` of ``camera``."""
    d = camera.ray_dirs_cam().astype(np.float32)
    z = np.ascontiguousarray(d[:, 2])
    col = np.tile(np.arange(camera.width_px, dtype=np.int64), camera.height_px)
    for a in (d, z, col):
        a.setflags(write=False)
    return PixelGrid(d, z, col)


@lru_cache(maxsize=1)
def _blas_controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def world_dirs(camera: PinholeCamera, R_world_cam: np.ndarray) -> np.ndarray:
    """Unit ray directions (H*W, 3) float32 of ``camera`` rotated into the world by
    ``R_world_cam`` (3, 3). The product runs on one BLAS thread: a multi-threaded BLAS leaves its
    workers spinning after this small product (measured: ~65 ms of a second core per stereo
    pair, slowing whatever else runs there)."""
    with _blas_controller().limit(limits=1, user_api="blas"):
        return pixel_grid(camera).dirs_cam @ np.asarray(R_world_cam, dtype=np.float32).T


def checked_pose(T: np.ndarray, what: str) -> np.ndarray:
    """``T`` as a float (4, 4) array; :class:`RenderError` naming ``what`` unless finite 4 x 4."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise RenderError(f"{what} must be a finite 4x4 pose, got shape {T.shape}")
    return T


def view_rays(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Rays (V * N, 6) float32 of V views that share the unit directions ``dirs`` (N, 3) and
    start at ``origins`` (V, 3), view after view (filled column by column: much faster in numpy
    than assigning strided (N, 3) blocks)."""
    origins = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
    n = len(dirs)
    rays = np.empty((len(origins), n, 6), dtype=np.float32)
    for c in range(3):
        rays[:, :, c] = origins[:, c:c + 1]
        rays[:, :, 3 + c] = dirs[:, c]
    return rays.reshape(-1, 6)

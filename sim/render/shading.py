"""Shading: seeded soil texture and per-rock albedos, Lambertian sun plus ambient light, the sky,
and the sensor (noise, optional blur, 8-bit quantisation). Float32 throughout."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from sim.render.config import Appearance, Lighting
from sim.world import World

_REMAP_COLS = 1024  # cv2.remap wants maps under 32767 px a side: long point lists are folded


def bilinear(grid: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) float32 of ``grid`` (h, w) float32 at continuous indices (column
    ``fx``, row ``fy``) (N,), edge values outside (as ``map_coordinates(order=1, mode="nearest")``)."""
    n = len(fx)
    rows = max(-(-n // _REMAP_COLS), 1)
    if n == rows * _REMAP_COLS and fx.dtype == fy.dtype == np.float32 and fx.flags.c_contiguous and fy.flags.c_contiguous:
        mx, my = fx, fy  # already a whole number of rows: no padded copy
    else:
        mx = np.zeros(rows * _REMAP_COLS, np.float32)
        my = np.zeros(rows * _REMAP_COLS, np.float32)
        mx[:n], my[:n] = fx, fy
    out = cv2.remap(grid, mx.reshape(rows, _REMAP_COLS), my.reshape(rows, _REMAP_COLS), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n]


class Shader:
    """Texture and per-rock albedos of one (world, appearance) pair."""

    def __init__(self, world: World, app: Appearance) -> None:
        rng = np.random.default_rng([app.seed, 7])
        xmin, xmax, ymin, ymax = world.extent
        cell = max(app.texture_scale_m / 2.0, 1e-3)
        nx = int((xmax - xmin) / cell) + 3
        ny = int((ymax - ymin) / cell) + 3
        # fine speckle plus a coarser mottling (weighted up: smoothing shrinks its spread)
        grid = gaussian_filter(rng.standard_normal((ny, nx)), 1.0)
        grid += 1.5 * gaussian_filter(rng.standard_normal((ny, nx)), 4.0)
        self._tex = (grid / (grid.std() + 1e-12)).astype(np.float32)
        self._origin = np.array([xmin - cell, ymin - cell], np.float32)
        self._cell = np.float32(cell)
        n = len(world.rocks)
        self._rock_albedo = (app.rock_albedo * np.exp(app.rock_albedo_spread * rng.standard_normal(n))).astype(np.float32)
        self.app = app

    def albedo(self, x: np.ndarray, y: np.ndarray, rock: np.ndarray) -> np.ndarray:
        """Albedo (N,) float32 of surface points at world ``x``, ``y`` (N,) float32 owned by
        ``rock`` (N,) (-1: soil)."""
        tex = bilinear(self._tex, (x - self._origin[0]) / self._cell, (y - self._origin[1]) / self._cell)
        amp = np.float32(self.app.texture_amplitude)
        out = np.float32(self.app.soil_albedo) * (1.0 + amp * tex)
        on_rock = np.flatnonzero(rock >= 0)
        if len(on_rock):
            out[on_rock] = self._rock_albedo[rock[on_rock]] * (1.0 + np.float32(0.3) * amp * tex[on_rock])
        return out


def cos_to_sun(normal: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Cosines (N,) float32 between unit normals (N, 3) and the unit ``sun`` (3,) float32."""
    return normal[:, 0] * sun[0] + normal[:, 1] * sun[1] + normal[:, 2] * sun[2]


def light(lighting: Lighting, sun: np.ndarray, cos_sun: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """Light (N,) float32 on surface points whose normal makes ``cos_sun`` (N,) with the sun:
    ambient + direct sun (Lambert) where ``lit``; flat ground under a sun above 30 deg gets 1."""
    lambert = np.clip(cos_sun, 0.0, 1.0)
    direct = np.float32((1.0 - lighting.ambient) / max(float(sun[2]), 0.5))
    return np.float32(lighting.ambient) + direct * lambert * lit


def grey_levels(app: Appearance, hit: np.ndarray, albedo: np.ndarray, light_: np.ndarray) -> np.ndarray:
    """Grey level (N,) float32 in [0, 1]: albedo x light where ``hit``, the sky level elsewhere."""
    grey = albedo * light_
    np.clip(grey, 0.0, 1.0, out=grey)
    grey[~hit] = np.float32(app.sky_level)
    return grey


def to_uint8(grey: np.ndarray, app: Appearance, rng: np.random.Generator | None) -> np.ndarray:
    """8-bit image (H, W) of grey levels (H, W) in [0, 1]: optional blur, additive Gaussian noise
    of ``app.noise_sigma`` grey levels drawn from ``rng`` (default: seeded by ``app.seed``)."""
    img = np.float32(255.0) * grey
    if app.blur_sigma_px > 0:
        img = gaussian_filter(img, app.blur_sigma_px)
    if app.noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng([app.seed, 11])
        noise = rng.standard_normal(img.shape, dtype=np.float32)
        noise *= np.float32(app.noise_sigma)
        img += noise
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


def shaded_grey(shader: Shader, lighting: Lighting, sun: np.ndarray, hit: np.ndarray, rock: np.ndarray,
                x: np.ndarray, y: np.ndarray, cos_sun: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """Grey levels (N,) float32 of N rays: surface points at world ``x``, ``y`` (N,) float32 owned
    by ``rock`` (N,), normal at ``cos_sun`` (N,) to the unit ``sun``, sunlit where ``lit``; sky
    where not ``hit``."""
    return grey_levels(shader.app, hit, shader.albedo(x, y, rock), light(lighting, sun, cos_sun, lit))

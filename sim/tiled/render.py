"""Nadir ("orbital") rendering of a tiled world from its surface model, one image tile at a time.

A ray caster over every rock mesh of a 128 m image tile (tens of thousands of rocks) costs seconds
per tile; the orbital view needs only the surface seen from above, so this renderer works on a
digital surface model at the image's ground sampling: terrain heights at the pixel centres (the
world's own terrain function: fractal noise plus craters), rocks splatted as the ellipsoid caps
of their meshes (higher surface wins, so it knows which rock each pixel shows). Shading is the
renderer's (:mod:`sim.render.shading`: Lambert sun + ambient, albedo x light, sensor noise and
8-bit quantisation); cast shadows are exact on the surface model: along each line towards the sun
a pixel is in shadow when some surface further sunward rises above its sun line (a running
maximum on the model resampled along the sun azimuth). Soil texture is seamless value noise and a
rock's albedo is a hash of its id, so neighbouring image tiles join without seams.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from sim.craters import stamp_relief
from sim.render.config import Appearance, Lighting, RenderError
from sim.render.shading import grey_levels, light, to_uint8
from sim.tiled.noise import FractalNoise, hash_uniform
from sim.tiled.world import TiledWorld

ROCK_SPLAT_MARGIN_M = 8.0  # rocks this far outside a tile can still shade into it
SHADOW_MARGIN_MAX_M = 96.0


@dataclass(frozen=True)
class OrbitalTile:
    """``image`` (H, W) uint8 grey (row 0 at the +y edge), ``rock`` (H, W) int64 id of the rock
    each pixel shows (-1: soil), ``extent`` (xmin, xmax, ymin, ymax) world metres, ``gsd_m``."""

    image: np.ndarray
    rock: np.ndarray
    extent: tuple[float, float, float, float]
    gsd_m: float


def _splat_rocks(dsm: np.ndarray, rid: np.ndarray, x0: float, y0: float, gsd: float, rocks) -> None:
    """Raise ``dsm`` (rows ascending in y from y0, columns from x0, pixel centres) to the rocks'
    ellipsoid caps; ``rid`` takes the id of the rock on top."""
    ny, nx = dsm.shape
    a = rocks.semi_m[:, 0]
    k_px = np.ceil(2.0 * a / gsd).astype(int) + 2
    flat_z, flat_id = dsm.ravel(), rid.ravel()
    for k in np.unique(k_px):
        sel = np.flatnonzero(k_px == k)
        cx, cy = rocks.xy_m[sel, 0], rocks.xy_m[sel, 1]
        j0 = np.floor((cx - x0) / gsd - 0.5 * k).astype(int)
        i0 = np.floor((cy - y0) / gsd - 0.5 * k).astype(int)
        off = np.arange(k + 1)
        jj = j0[:, None, None] + off[None, None, :]
        ii = i0[:, None, None] + off[None, :, None]
        px, py = x0 + (jj + 0.5) * gsd - cx[:, None, None], y0 + (ii + 0.5) * gsd - cy[:, None, None]
        c, s = np.cos(rocks.yaw_rad[sel])[:, None, None], np.sin(rocks.yaw_rad[sel])[:, None, None]
        u, v = px * c + py * s, -px * s + py * c
        q = (u / rocks.semi_m[sel, 0, None, None]) ** 2 + (v / rocks.semi_m[sel, 1, None, None]) ** 2
        z = rocks.xyz_m[sel, 2, None, None] + rocks.semi_m[sel, 2, None, None] * np.sqrt(np.clip(1.0 - q, 0.0, None))
        ok = (q < 1.0) & (ii >= 0) & (ii < ny) & (jj >= 0) & (jj < nx)
        idx = (np.broadcast_to(ii, ok.shape) * nx + np.broadcast_to(jj, ok.shape))[ok]
        val = z[ok]
        ids = np.broadcast_to(rocks.id[sel, None, None], ok.shape)[ok]
        order = np.argsort(val, kind="stable")
        idx, val, ids = idx[order], val[order], ids[order]
        up = val > flat_z[idx]
        flat_z[idx[up]] = val[up]  # duplicates: the last (highest) value wins
        flat_id[idx[up]] = ids[up]


def _shadowed(dsm: np.ndarray, gsd: float, sun_az_deg: float, sun_el_deg: float) -> np.ndarray:
    """Boolean (H, W): pixels of ``dsm`` (image orientation, row 0 at +y) in cast shadow."""
    H, W = dsm.shape
    az = math.radians(sun_az_deg)
    s = np.array([-math.sin(az), math.cos(az)])  # sunward step in (row, col): +y is -row
    n = np.array([s[1], -s[0]])
    c0 = np.array([(H - 1) / 2.0, (W - 1) / 2.0])
    R = math.ceil(0.5 * math.hypot(H, W)) + 1
    u = np.arange(-R, R + 1, dtype=float)
    uu, ww = np.meshgrid(u, u)  # rotated grid: rows = w (across), columns = u (towards the sun)
    rows = c0[0] + uu * s[0] + ww * n[0]
    cols = c0[1] + uu * s[1] + ww * n[1]
    h = map_coordinates(dsm, [rows, cols], order=1, mode="constant", cval=-1e9)
    g = h - u[None, :] * gsd * math.tan(math.radians(sun_el_deg))
    ahead = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]
    ahead = np.concatenate([ahead[:, 1:], np.full((len(u), 1), -np.inf)], axis=1)
    shade = (ahead > g + 1e-3).astype(np.float32)
    # back to the image: its pixels' (u, w) coordinates
    pi, pj = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    d = np.stack([pi - c0[0], pj - c0[1]])
    pu, pw = d[0] * s[0] + d[1] * s[1], d[0] * n[0] + d[1] * n[1]
    back = map_coordinates(shade, [pw + R, pu + R], order=1, mode="nearest")
    return back > 0.5


class OrbitalRenderer:
    """Renders image tiles of ``world`` at ``gsd_m`` under ``lighting`` and ``appearance``."""

    def __init__(self, world: TiledWorld, gsd_m: float, lighting: Lighting = Lighting(),
                 appearance: Appearance = Appearance(), min_rock_px: float = 0.5) -> None:
        if not gsd_m > 0:
            raise RenderError(f"gsd_m must be > 0, got {gsd_m}")
        self.world, self.gsd_m, self.lighting, self.app = world, float(gsd_m), lighting, appearance
        self.min_rock_m = min_rock_px * gsd_m
        self._texture = FractalNoise(world.seed ^ 0x7E47, 1.0, largest_m=4.0 * appearance.texture_scale_m,
                                     smallest_m=appearance.texture_scale_m, hurst=0.0)
        self._sun = lighting.sun_dir()

    def shadow_margin_m(self, extent) -> float:
        """How far sunward of ``extent`` a surface can cast a shadow into it: a crater's rim stands
        at most ~0.25 D above its floor, so its shadow reaches 0.25 D / tan(sun elevation)."""
        tan_el = math.tan(math.radians(self.lighting.sun_elevation_deg))
        c = self.world.craters_near(extent, reach_radii=1.0 + 0.5 / tan_el, d_min_m=8.0)
        reach = 0.25 * float(c.diameter_m.max()) / tan_el if len(c) else 0.0
        return float(np.clip(reach, ROCK_SPLAT_MARGIN_M, SHADOW_MARGIN_MAX_M))

    def tile(self, extent: tuple[float, float, float, float], rng: np.random.Generator | None = None) -> OrbitalTile:
        """The image of ``extent`` (its size a whole number of pixels)."""
        gsd = self.gsd_m
        xmin, xmax, ymin, ymax = extent
        W, H = round((xmax - xmin) / gsd), round((ymax - ymin) / gsd)
        if W < 1 or H < 1:
            raise RenderError(f"extent {extent} is smaller than one {gsd} m pixel")
        # the surface model reaches far only on the sunward sides (where shadows come from)
        far = math.ceil(self.shadow_margin_m(extent) / gsd)
        near = math.ceil(ROCK_SPLAT_MARGIN_M / gsd)
        az = math.radians(self.lighting.sun_azimuth_deg)
        west, east = (far, near) if math.cos(az) < 0 else (near, far)
        south, north = (far, near) if math.sin(az) < 0 else (near, far)
        xs = xmin + (np.arange(-west, W + east) + 0.5) * gsd
        ys = ymin + (np.arange(-south, H + north) + 0.5) * gsd  # ascending
        z = self.world.noise.grid(xs, ys)
        ext_e = (xs[0], xs[-1], ys[0], ys[-1])
        cr = self.world.craters_near(ext_e)
        z = stamp_relief(z, ext_e, cr.xy_m, cr.diameter_m, cr.degradation)
        rid = np.full(z.shape, -1, dtype=np.int64)
        m = ROCK_SPLAT_MARGIN_M
        rocks = self.world.rocks_in((xmin - m, xmax + m, ymin - m, ymax + m), self.min_rock_m)
        if len(rocks):
            _splat_rocks(z, rid, xs[0] - 0.5 * gsd, ys[0] - 0.5 * gsd, gsd, rocks)
        dsm, rid = z[::-1], rid[::-1]  # image orientation: row 0 at +y
        gy_img, gx = np.gradient(dsm, gsd)
        nrm = np.stack([-gx, gy_img, np.ones_like(gx)], axis=-1)  # d/drow = -d/dy
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        sun = self._sun
        cos_sun = (nrm @ sun).astype(np.float32)
        lit = ~_shadowed(dsm, gsd, self.lighting.sun_azimuth_deg, self.lighting.sun_elevation_deg)
        inner = (slice(north, north + H), slice(west, west + W))  # image rows run from +y
        albedo = self._albedo(xs[west:west + W], ys[south:south + H][::-1], rid[inner])
        grey = grey_levels(self.app, np.ones(albedo.shape, bool), albedo,
                           light(self.lighting, sun.astype(np.float32), cos_sun[inner], lit[inner]))
        image = to_uint8(grey, self.app, rng)
        return OrbitalTile(image, rid[inner].copy(), (xmin, xmin + W * gsd, ymax - H * gsd, ymax), gsd)

    def _albedo(self, xs: np.ndarray, ys_desc: np.ndarray, rid: np.ndarray) -> np.ndarray:
        app = self.app
        tex = self._texture.grid(xs, ys_desc) / 1.2
        out = (app.soil_albedo * (1.0 + app.texture_amplitude * tex)).astype(np.float32)
        on = rid >= 0
        if on.any():
            u = hash_uniform(self.world.seed, 0xA1BED0, rid[on], np.zeros(int(on.sum()), dtype=np.int64))
            gauss = np.sqrt(3.0) * u  # unit variance
            out[on] = (app.rock_albedo * np.exp(app.rock_albedo_spread * gauss) * (1.0 + 0.3 * app.texture_amplitude * tex[on]))
        return out

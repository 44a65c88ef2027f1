"""Cratered orbital scenes for the crater detector: a seeded patch of terrain (fractal relief,
wind-blown bedforms, a crater population of :mod:`sim.craters`, ejecta blocks as rock meshes)
rendered at nadir by :mod:`sim.render` under a random sun, with albedo variation on top.

``render_crater_scene(SceneVariation(), rng)`` -> :class:`CraterScene`: the clean image as float
grey levels in [0, 1] (no sensor yet: :mod:`sim.crater_datasets` adds blur, noise, quantisation,
JPEG), the craters in pixel units, and the scene's ground sample distance and extent. Sizes are
drawn in pixels, so one scene stands for HiRISE (0.25 m/px) and CTX (6 m/px) alike: the
equilibrium crater population is nearly scale-free, and ejecta blocks appear only where they
are at least a pixel and a half wide.

Rendering is supersampled (``supersample`` rays per pixel side, averaged): a 4 px crater is then
a smooth bowl rather than a few facets of the heightmap.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from sim.craters import (
    INFLUENCE_RADIUS,
    Craters,
    CraterSFD,
    EjectaConfig,
    ejecta_blocks,
    sample_craters,
    stamp_craters,
)
from sim.render import Appearance, Lighting
from sim.render.shading import Shader, cos_to_sun, grey_levels, light
from sim.rocks import Rocks
from sim.terrain import Heightmap, fractal_heightmap
from sim.world import World

# crater populations are drawn per diameter band (px) with a margin of the band's influence
# radius, so craters centred outside the image still shape its edges
SIZE_BANDS_PX = (1.5, 6.0, 24.0, 96.0, 400.0)
VISIBLE_DEPTH_RATIO = 1.5  # a bowl no deeper than this x the terrain relief at its scale is hidden


def relief_at_scales(z_m: np.ndarray, step: int, levels: int = 8) -> np.ndarray:
    """Rms relief (levels,) m of the heights ``z_m`` sampled every ``step`` nodes (one per pixel)
    in octaves: entry k is the Laplacian-pyramid band of features about 2^(k+1) px across."""
    z = np.ascontiguousarray(z_m[::step, ::step], dtype=np.float32)
    out = np.zeros(levels)
    for k in range(levels):
        if min(z.shape) < 8:
            break
        down = cv2.pyrDown(z)
        band = z - cv2.pyrUp(down, dstsize=(z.shape[1], z.shape[0]))
        # the border's 4 px leave the pyramid's edge effects out where the band keeps 8 px or more
        # inside (an 8 px level, as 1024 px scenes reach, was once left empty: NaN, every crater
        # of that size then unseen)
        out[k] = float(np.std(band[4:-4, 4:-4] if min(band.shape) >= 16 else band))
        z = down
    return out


def visible_craters(diameters_px: np.ndarray, depth_m: np.ndarray, relief_m: np.ndarray) -> np.ndarray:
    """Boolean (N,): craters whose depth is at least VISIBLE_DEPTH_RATIO x the rms relief of the
    terrain features no larger than themselves (``relief_m`` from :func:`relief_at_scales`)."""
    scale_px = 2.0 ** (np.arange(len(relief_m)) + 1)
    var = np.array([np.sum(relief_m[scale_px <= d] ** 2) for d in np.ravel(diameters_px)])
    return np.asarray(depth_m) >= VISIBLE_DEPTH_RATIO * np.sqrt(var)


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    lo, hi = np.log(lo_hi)
    return float(np.exp(rng.uniform(lo, hi)))


def smooth_noise(shape: tuple[int, int], scale_px: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-variance random field (ny, nx) float32 smooth over ``scale_px``: white
    noise on a grid of that spacing, smoothed and upsampled (cheap where ``scale_px`` is large)."""
    ny, nx = shape
    k = max(float(scale_px) / 2.0, 1.0)
    small = gaussian_filter(rng.standard_normal((int(ny / k) + 3, int(nx / k) + 3)), 1.0)
    f = cv2.resize(small.astype(np.float32), (nx, ny), interpolation=cv2.INTER_CUBIC)
    return (f - f.mean()) / (f.std() + 1e-12)


@dataclass(frozen=True)
class SceneVariation:
    """Ranges of the cratered scenes (uniform unless stated)."""

    size_px: int = 640
    supersample: int = 2
    gsd_m: tuple[float, float] = (0.25, 6.0)  # log-uniform: HiRISE to CTX
    age_gyr: tuple[float, float] = (0.02, 3.5)  # log-uniform surface age (crater density)
    density_scale: tuple[float, float] = (0.4, 1.5)  # log-uniform
    large_crater_boost: tuple[float, float] = (1.0, 1.0)  # log-uniform extra density above 24 px
    d_max_px: float = 260.0
    slope_pct: tuple[float, float] = (0.2, 5.0)  # log-uniform: relief over the patch side
    persistence: tuple[float, float] = (0.3, 0.55)  # of the large-scale fractal relief
    roughness_gsd: tuple[float, float] = (0.02, 0.5)  # log-uniform: rms relief at 8 px, in pixels
    roughness_decay: tuple[float, float] = (0.35, 0.7)  # per halving of the scale, 8 px to 1 px
    bedform_p: float = 0.35  # share of scenes with ripple fields
    block_p: float = 0.6  # share of scenes whose fresh craters carry ejecta blocks
    sun_elevation_deg: tuple[float, float] = (12.0, 65.0)
    ambient: tuple[float, float] = (0.04, 0.3)
    albedo_field_sigma: tuple[float, float] = (0.0, 0.35)  # large-scale albedo patches (log)
    floor_albedo_p: float = 0.3  # share of craters (D >= 4 px) with a bright or dark floor fill


@dataclass(frozen=True)
class CraterScene:
    """A rendered scene: ``grey`` (H, W) float32 in [0, 1], ``craters`` (world frame) with their
    pixel centres ``centres_px`` (N, 2) (column, row; pixel edges at integers) and rim diameters
    ``diameters_px`` (N,), ``gsd_m`` and ``extent`` (xmin, xmax, ymin, ymax) of the image."""

    grey: np.ndarray
    craters: Craters
    centres_px: np.ndarray
    diameters_px: np.ndarray
    gsd_m: float
    extent: tuple[float, float, float, float]
    lighting: Lighting
    visible: np.ndarray  # (N,) bool: bowl deeper than VISIBLE_DEPTH_RATIO x the terrain's relief at its scale
    grey_without_craters: np.ndarray | None = None  # the same ground and sun without the craters (on request)


def scene_craters(extent: tuple[float, float, float, float], gsd_m: float, sfd: CraterSFD, boost: float,
                  d_max_px: float, rng: np.random.Generator) -> Craters:
    """Craters of ``sfd`` whose relief can reach ``extent``, drawn per size band (pixels) over
    the extent grown by each band's influence radius; bands above 24 px scaled by ``boost``."""
    xmin, xmax, ymin, ymax = extent
    parts, base = [], 0
    for lo, hi in pairwise(SIZE_BANDS_PX):
        hi = min(hi, d_max_px)
        if hi <= lo:
            break
        pad = INFLUENCE_RADIUS * 0.5 * hi * gsd_m
        box = (xmin - pad, xmax + pad, ymin - pad, ymax + pad)
        band_sfd = sfd if lo < 24.0 else CraterSFD(sfd.age_gyr, d_min_m=sfd.d_min_m, d_max_m=sfd.d_max_m,
                                                    density_scale=sfd.density_scale * boost)
        c = sample_craters(band_sfd, box, rng, d_lo_m=lo * gsd_m, d_hi_m=hi * gsd_m, id_base=base)
        parts.append(c.reaching(extent, INFLUENCE_RADIUS))
        base += len(c)
    return Craters.concat(parts)


def terrain_heights(extent: tuple[float, float, float, float], spacing_m: float, side_m: float,
                    var: SceneVariation, rng: np.random.Generator) -> np.ndarray:
    """Heights (ny, nx) m of the base terrain on the grid of ``extent`` at ``spacing_m``: the
    fractal relief of :func:`sim.terrain.fractal_heightmap` on a coarse grid (its large Gaussian
    octaves are costly at full resolution), upsampled, plus fine fractal roughness."""
    nx = round((extent[1] - extent[0]) / spacing_m) + 1
    ny = round((extent[3] - extent[2]) / spacing_m) + 1
    relief = _log_uniform(rng, var.slope_pct) / 100.0 * side_m
    coarse = fractal_heightmap(extent, relief, side_m / 96.0, rng, largest_scale_m=side_m * rng.uniform(0.3, 1.0),
                               octaves=5, persistence=rng.uniform(*var.persistence))
    z = cv2.resize(coarse.z_m.astype(np.float32), (nx, ny), interpolation=cv2.INTER_CUBIC).astype(float)
    # roughness below the coarse grid: octaves from 8 px down to 1 px
    amp = _log_uniform(rng, var.roughness_gsd) * spacing_m * var.supersample
    decay = rng.uniform(*var.roughness_decay)
    for scale_px in (8.0, 4.0, 2.0, 1.0):
        layer = gaussian_filter(rng.standard_normal((ny, nx)), scale_px * var.supersample / 2.0)
        z += amp * layer / (layer.std() + 1e-12)
        amp *= decay
    return z


def bedforms(shape: tuple[int, int], spacing_m: float, gsd_m: float, rng: np.random.Generator) -> np.ndarray:
    """Heights (ny, nx) m of a patchy ripple field: sinuous crests 4-30 px apart, about a tenth of
    their wavelength high, in smooth random patches."""
    ny, nx = shape
    wavelength_m = _log_uniform(rng, (4.0, 30.0)) * gsd_m
    th = rng.uniform(0, np.pi)
    yy, xx = np.mgrid[0:ny, 0:nx] * spacing_m
    warp = rng.uniform(1.0, 6.0) * smooth_noise(shape, max(nx, ny) / 6.0, rng)
    phase = 2 * np.pi * (xx * np.cos(th) + yy * np.sin(th)) / wavelength_m + warp
    patch = smooth_noise(shape, max(nx, ny) / rng.uniform(2.0, 6.0), rng)
    patch = np.clip((patch - rng.uniform(-1.0, 1.0)) * 2.0, 0.0, 1.0)
    return rng.uniform(0.03, 0.1) * wavelength_m * np.sin(phase) * patch


def stamp_blocks(z_m: np.ndarray, spacing_m: float, extent: tuple[float, float, float, float], craters: Craters,
                 gsd_m: float, seed: int, max_blocks: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Heights ``z_m`` (ny, nx) (row i at ymin + i spacing) with the ejecta blocks of fresh
    craters (:func:`sim.craters.ejecta_blocks`) at least 1.5 px wide stamped on as half-buried
    spheroids (height 0.6 of the width), and the boolean mask (ny, nx) of block tops."""
    blocks = ejecta_blocks(craters, seed, EjectaConfig(min_block_m=1.5 * gsd_m, max_block_m=max(3.0, 4.0 * gsd_m)))
    z = np.array(z_m, dtype=float)
    mask = np.zeros(z.shape, dtype=bool)
    ny, nx = z.shape
    for (x, y), d in zip(blocks.xy_m[:max_blocks], blocks.diameter_m[:max_blocks]):
        r = 0.5 * d / spacing_m
        j, i = (x - extent[0]) / spacing_m, (y - extent[2]) / spacing_m
        j0, j1, i0, i1 = max(int(j - r), 0), min(int(j + r) + 2, nx), max(int(i - r), 0), min(int(i + r) + 2, ny)
        if j1 <= j0 or i1 <= i0:
            continue
        ii, jj = np.mgrid[i0:i1, j0:j1]
        q = 1.0 - ((jj - j) ** 2 + (ii - i) ** 2) / max(r * r, 1e-9)
        top = np.min(z[i0:i1, j0:j1]) + 0.6 * d * np.sqrt(np.clip(q, 0.0, None)) - 0.1 * d
        on = (q > 0) & (top > z[i0:i1, j0:j1])
        z[i0:i1, j0:j1] = np.where(on, top, z[i0:i1, j0:j1])
        mask[i0:i1, j0:j1] |= on
    return z, mask


def sun_shadows(z_m: np.ndarray, spacing_m: float, lighting: Lighting) -> np.ndarray:
    """Boolean (ny, nx): grid points of the heightfield ``z_m`` (row i at ymin + i spacing) that
    the sun sees. A point is lit when no point towards the sun rises above its sun ray:
    z_i - u_i tan(e) >= max over u_j > u_i of (z_j - u_j tan(e)), u the distance along the sun
    azimuth; computed on the grid turned so that the sun shines along its rows."""
    ny, nx = z_m.shape
    az = np.deg2rad(lighting.sun_azimuth_deg)
    tan_e = np.tan(np.deg2rad(lighting.sun_elevation_deg))
    up = 2  # the turned grid samples twice as finely: interpolation there must not shave the rims
    diag = int(np.ceil(up * np.hypot(nx, ny))) + 4
    c, s = np.cos(az) / up, np.sin(az) / up
    # turned grid (diag x diag) -> heightfield grid: its +column axis points towards the sun
    M = np.array([[c, -s, 0.0], [s, c, 0.0]])
    M[:, 2] = np.array([(nx - 1) / 2, (ny - 1) / 2]) - M[:, :2] @ np.array([(diag - 1) / 2, (diag - 1) / 2])
    M = M.astype(np.float32)
    zr = cv2.warpAffine(z_m.astype(np.float32), M, (diag, diag), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)
    inside = cv2.warpAffine(np.ones((ny, nx), np.uint8), M, (diag, diag), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    w = zr - (np.arange(diag, dtype=np.float32) * np.float32(spacing_m / up * tan_e))[None, :]
    w[inside == 0] = -np.inf  # beyond the heightfield nothing blocks the sun
    ahead = np.maximum.accumulate(w[:, ::-1], axis=1)[:, ::-1]
    ahead = np.concatenate([ahead[:, 1:], np.full((diag, 1), -np.inf, np.float32)], axis=1)
    lit_r = (w >= ahead - np.float32(0.02 * spacing_m)).astype(np.uint8)
    lit = cv2.warpAffine(lit_r, M, (nx, ny), flags=cv2.INTER_NEAREST)
    return lit.astype(bool)


def shade_heightfield(terrain: Heightmap, app: Appearance, lighting: Lighting, rock_mask: np.ndarray) -> np.ndarray:
    """Nadir grey levels (ny, nx) float32 of the heightfield's grid points, rows from +y down (the
    image convention of :mod:`sim.render.nadir`): the shading of :mod:`sim.render.shading`
    (texture, Lambert sun plus ambient light where lit), ``rock_mask`` points given rock albedo."""
    z = terrain.z_m
    dx, dy = terrain.spacing_m
    gy, gx = np.gradient(z, dy, dx)
    normal = np.stack([-gx, -gy, np.ones_like(z)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    sun = lighting.sun_dir().astype(np.float32)
    normal = normal.reshape(-1, 3).astype(np.float32)
    cos_sun = cos_to_sun(normal, sun)
    lit = sun_shadows(z, dx, lighting).ravel() & (cos_sun > 0)
    ny, nx = z.shape
    xmin, _, ymin, _ = terrain.extent
    xs = np.ascontiguousarray(np.broadcast_to((xmin + dx * np.arange(nx, dtype=np.float32))[None, :], (ny, nx)).ravel())
    ys = np.ascontiguousarray(np.broadcast_to((ymin + dy * np.arange(ny, dtype=np.float32))[:, None], (ny, nx)).ravel())
    world = World(name="craters", terrain=terrain, rocks=Rocks.from_meshes([]))
    rock = np.where(rock_mask.ravel(), 0, -1).astype(np.int32)
    shader = Shader(world, app)
    albedo = shader.albedo(xs, ys, np.full(len(xs), -1, np.int32))
    albedo[rock >= 0] *= np.float32(app.rock_albedo / app.soil_albedo)
    grey = grey_levels(app, np.ones(len(xs), bool), albedo, light(lighting, sun, cos_sun, lit))
    return grey.reshape(ny, nx)[::-1]


def albedo_multipliers(shape_hw: tuple[int, int], centres_px: np.ndarray, diameters_px: np.ndarray,
                       var: SceneVariation, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(large-scale albedo patches, crater floor fills) as multipliers (H, W) float32 of the
    shaded grey levels; the floors belong to the craters, the patches to the ground."""
    h, w = shape_hw
    patches = np.ones((h, w), np.float32)
    sigma = rng.uniform(*var.albedo_field_sigma)
    if sigma > 0:
        patches = np.exp(sigma * smooth_noise((h, w), max(h, w) / rng.uniform(1.5, 8.0), rng)).astype(np.float32)
    floors = np.ones((h, w), np.float32)
    pick = np.flatnonzero((diameters_px >= 4.0) & (rng.random(len(diameters_px)) < var.floor_albedo_p))
    for k in pick:
        (cx, cy), r = centres_px[k], 0.5 * diameters_px[k]
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 2, w)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 2, h)
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        rho = np.hypot(xx + 0.5 - cx, yy + 0.5 - cy) / r
        m = np.clip((0.9 - rho) / 0.3, 0.0, 1.0) * rng.uniform(0.4, 1.0)
        floors[y0:y1, x0:x1] *= (1.0 + (_log_uniform(rng, (0.6, 1.6)) - 1.0) * m).astype(np.float32)
    return patches, floors


def render_crater_scene(var: SceneVariation, rng: np.random.Generator, without_craters: bool = False) -> CraterScene:
    """One seeded cratered scene of ``var.size_px`` square pixels (see the module doc).

    ``without_craters``: also render the same ground without them (no crater relief, ejecta
    blocks or floor fills; the same terrain, albedo and sun) as ``grey_without_craters``, for
    the craters' photometric signal (:func:`sim.crater_datasets.signal_to_clutter`); the scene
    itself and the generator's state are the same either way (one more shading pass)."""
    n, ss = var.size_px, var.supersample
    gsd = _log_uniform(rng, var.gsd_m)
    spacing = gsd / ss
    side = n * gsd
    extent = (-side / 2, side / 2, -side / 2, side / 2)
    # heightmap nodes at the centres of the supersampled pixels, plus a margin whose rims can
    # cast shadows into the image
    m = 24 * ss
    t_ext = (extent[0] + 0.5 * spacing - m * spacing, extent[1] - 0.5 * spacing + m * spacing,
             extent[2] + 0.5 * spacing - m * spacing, extent[3] - 0.5 * spacing + m * spacing)
    z = terrain_heights(t_ext, spacing, side, var, rng)
    if rng.random() < var.bedform_p:
        z += bedforms(z.shape, spacing, gsd, rng)
    relief = relief_at_scales(z, ss)
    sfd = CraterSFD(age_gyr=_log_uniform(rng, var.age_gyr), d_min_m=SIZE_BANDS_PX[0] * gsd,
                    d_max_m=min(var.d_max_px * gsd, 2000.0), density_scale=_log_uniform(rng, var.density_scale))
    craters = scene_craters(extent, gsd, sfd, _log_uniform(rng, var.large_crater_boost), var.d_max_px, rng)
    z_ground = z
    z = stamp_craters(Heightmap(z, t_ext), craters).z_m
    seed = int(rng.integers(1 << 31))
    rock_mask = np.zeros(z.shape, dtype=bool)
    if rng.random() < var.block_p:
        z, rock_mask = stamp_blocks(z, spacing, t_ext, craters, gsd, seed)
    soil = rng.uniform(0.2, 0.45)  # the camera sets the exposure: this only keeps bright slopes unclipped
    app = Appearance(soil_albedo=soil, rock_albedo=soil * rng.uniform(0.7, 1.5),
                     texture_amplitude=rng.uniform(0.02, 0.2), texture_scale_m=gsd * _log_uniform(rng, (1.5, 40.0)),
                     noise_sigma=0.0, blur_sigma_px=0.0, seed=seed)
    light = Lighting(sun_elevation_deg=rng.uniform(*var.sun_elevation_deg), sun_azimuth_deg=rng.uniform(0.0, 360.0),
                     ambient=rng.uniform(*var.ambient))
    fine = shade_heightfield(Heightmap(z, t_ext), app, light, rock_mask)[m:-m, m:-m]
    grey = cv2.resize(fine, (n, n), interpolation=cv2.INTER_AREA)
    centres = np.column_stack([(craters.xy_m[:, 0] - extent[0]) / gsd, (extent[3] - craters.xy_m[:, 1]) / gsd])
    diam = craters.diameter_m / gsd
    patches, floors = albedo_multipliers(grey.shape, centres, diam, var, rng)
    grey = np.clip(grey.astype(np.float32) * patches * floors, 0.0, 1.0)
    ground = None
    if without_craters:
        bare = shade_heightfield(Heightmap(z_ground, t_ext), app, light, np.zeros(z_ground.shape, dtype=bool))[m:-m, m:-m]
        ground = np.clip(cv2.resize(bare, (n, n), interpolation=cv2.INTER_AREA).astype(np.float32) * patches, 0.0, 1.0)
    return CraterScene(grey, craters, centres.reshape(-1, 2), diam, gsd, extent, light,
                       visible_craters(diam, craters.depth_m, relief), ground)

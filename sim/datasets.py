"""Rendered detection data sets: procedurally varied worlds, nadir tiles and rover views, and box
labels made from the renderer's exact per-pixel rock instance ids.

A rock's box is the bounding box of the pixels where it is the first surface hit (so a partly
occluded rock gets the box of its visible part). Rocks whose visible part is too small to be
called a rock by any observer (fewer than ``min_area_px`` pixels or a box side under
``min_side_px``) become *ignore* boxes: a detection on them is neither a true nor a false
positive, as COCO treats its "crowd" regions. Training and evaluation use disjoint seed streams
(``split`` "train", "val" for choosing the score threshold, or "eval"), so evaluation worlds
are never seen in training.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterator

import numpy as np
from scipy.ndimage import find_objects

from sim.config import StereoConfig
from sim.render import Appearance, Lighting, NadirRender, PinholeCamera, Renderer, StereoRender
from sim.rocks import generate_rocks
from sim.sensors.stereo import StereoCamera
from sim.terrain import fractal_heightmap
from sim.world import World

SPLITS = {"train": 0, "eval": 1, "val": 2}


@dataclass(frozen=True)
class BoxLabels:
    """Boxes of one image: ``boxes_xyxy`` (K, 4) pixel edges (x0, y0, x1, y1), ``rock`` (K,) rows
    in ``world.rocks``, ``area_px`` (K,) visible pixels, ``ignore`` (K,) True for too-small rocks."""

    boxes_xyxy: np.ndarray
    rock: np.ndarray
    area_px: np.ndarray
    ignore: np.ndarray

    @property
    def positives(self) -> np.ndarray:
        """(P, 4) boxes that count as ground truth."""
        return self.boxes_xyxy[~self.ignore]


def box_labels(instance: np.ndarray, min_area_px: float, min_side_px: float) -> BoxLabels:
    """Box labels from an instance image (H, W) of rock rows (-1: none)."""
    inst = np.asarray(instance)
    slices = find_objects(inst + 1)
    rows, boxes = [], []
    for k, sl in enumerate(slices):
        if sl is not None:
            rows.append(k)
            boxes.append((sl[1].start, sl[0].start, sl[1].stop, sl[0].stop))
    rock = np.asarray(rows, dtype=np.int64)
    boxes_a = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
    counts = np.bincount(inst[inst >= 0].ravel(), minlength=int(rock.max(initial=-1)) + 1)
    area = counts[rock].astype(float) if len(rock) else np.zeros(0)
    side = np.minimum(boxes_a[:, 2] - boxes_a[:, 0], boxes_a[:, 3] - boxes_a[:, 1])
    ignore = (area < min_area_px) | (side < min_side_px)
    return BoxLabels(boxes_a, rock, area, ignore)


@dataclass(frozen=True)
class WorldVariation:
    """Ranges of the procedural worlds (uniform unless stated)."""

    size_m: float = 30.0
    relief_m: tuple[float, float] = (0.3, 4.0)  # per 40 m of world side
    rock_density_per_m2: tuple[float, float] = (0.1, 1.8)  # log-uniform
    alpha: tuple[float, float] = (1.7, 2.4)
    d_max_m: tuple[float, float] = (0.8, 1.6)
    resolution_m: float = 0.15


def random_world(rng: np.random.Generator, var: WorldVariation = WorldVariation(), size_m: float | None = None) -> World:
    """A procedurally varied square world (terrain + rocks) of side ``size_m`` (default ``var.size_m``)."""
    s = float(size_m or var.size_m)
    extent = (-s / 2, s / 2, -s / 2, s / 2)
    terrain = fractal_heightmap(extent, rng.uniform(*var.relief_m) * s / 40.0, var.resolution_m, rng)
    lo, hi = np.log(var.rock_density_per_m2)
    n = int(np.exp(rng.uniform(lo, hi)) * s * s)
    rocks = generate_rocks(terrain, n, rng, d_min=0.1, d_max=rng.uniform(*var.d_max_m), alpha=rng.uniform(*var.alpha))
    return World(name="procedural", terrain=terrain, rocks=rocks)


def random_appearance(rng: np.random.Generator, *, nadir: bool) -> tuple[Appearance, Lighting]:
    """Random albedos, texture, noise and sun for one image."""
    soil = rng.uniform(0.45, 0.75)
    app = Appearance(
        soil_albedo=soil, rock_albedo=soil * rng.uniform(0.65, 1.1), rock_albedo_spread=rng.uniform(0.05, 0.25),
        texture_amplitude=rng.uniform(0.04, 0.18), texture_scale_m=rng.uniform(0.2, 0.8),
        sky_level=rng.uniform(0.4, 0.8), noise_sigma=rng.uniform(0.5, 4.0),
        blur_sigma_px=rng.uniform(0.0, 0.9) if nadir else 0.0, seed=int(rng.integers(1 << 31)),
    )
    light = Lighting(sun_elevation_deg=rng.uniform(15.0, 65.0), sun_azimuth_deg=rng.uniform(0.0, 360.0),
                     ambient=rng.uniform(0.12, 0.35))
    return app, light


@dataclass(frozen=True)
class NadirSetConfig:
    """Nadir tiles: ``tile_px`` square tiles at a ground sample distance drawn from ``gsd_m``."""

    tile_px: int = 640
    gsd_m: tuple[float, float] = (0.035, 0.07)
    tiles_per_world: int = 2
    min_area_px: float = 20.0  # about a 5 px wide rock
    min_side_px: float = 4.0
    world: WorldVariation = WorldVariation()


@dataclass(frozen=True)
class Sample:
    """One labelled image: ``image`` (H, W) uint8, ``labels`` and, for rover views, the stereo render."""

    image: np.ndarray
    labels: BoxLabels
    stereo: StereoRender | None = None
    nadir: NadirRender | None = None
    world: World | None = None


def nadir_samples(n: int, seed: int, split: str = "train", cfg: NadirSetConfig = NadirSetConfig()) -> Iterator[Sample]:
    """``n`` labelled nadir tiles from procedurally varied worlds (seeded; ``split`` picks the stream)."""
    k = 0
    w_idx = 0
    while k < n:
        rng = np.random.default_rng([seed, SPLITS[split], 17, w_idx])
        w_idx += 1
        gsd = rng.uniform(*cfg.gsd_m)
        side = cfg.tile_px * gsd
        world = random_world(rng, cfg.world, size_m=side + 2.0)
        for _ in range(min(cfg.tiles_per_world, n - k)):
            app, light = random_appearance(rng, nadir=True)
            x0 = -side / 2 + rng.uniform(-0.8, 0.8)
            y0 = -side / 2 + rng.uniform(-0.8, 0.8)
            r = Renderer(world, app).nadir(gsd, light, extent=(x0, x0 + side, y0, y0 + side), rng=rng)
            yield Sample(r.image, box_labels(r.instance, cfg.min_area_px, cfg.min_side_px), nadir=r, world=world)
            k += 1


@dataclass(frozen=True)
class RoverSetConfig:
    """Rover views: the mast camera of :class:`sim.config.StereoConfig` rendered at ``width_px``."""

    width_px: int = 640
    views_per_world: int = 4
    min_area_px: float = 30.0
    min_side_px: float = 5.0
    max_range_m: float = 12.0  # rocks farther than this are ignore boxes
    stereo: StereoConfig = StereoConfig()
    world: WorldVariation = WorldVariation()


def rover_camera(cfg: StereoConfig, width_px: int) -> PinholeCamera:
    """The mast camera of ``cfg`` (same field of view and aspect) at ``width_px`` columns."""
    height = int(round(cfg.height_px * width_px / cfg.width_px))
    return PinholeCamera.from_fov(width_px, height, cfg.hfov_deg)


def rover_pose(world: World, xy: np.ndarray, yaw_rad: float, base_height_m: float = 0.15) -> np.ndarray:
    """T_world_base (4, 4) of a rover standing at ``xy`` (2,) with ``yaw_rad``, tilted with the terrain."""
    n = world.normal_at(np.reshape(xy, (1, 2)))[0]
    fwd = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    x = fwd - n * (fwd @ n)
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, n])
    T[:3, 3] = [xy[0], xy[1], world.height_at(np.reshape(xy, (1, 2)))[0] + base_height_m]
    return T


def rover_samples(n: int, seed: int, split: str = "train", cfg: RoverSetConfig = RoverSetConfig()) -> Iterator[Sample]:
    """``n`` labelled left-camera stereo renders from rover poses in procedurally varied worlds."""
    cam = rover_camera(cfg.stereo, cfg.width_px)
    T_base_cam = StereoCamera.from_config(cfg.stereo).T_base_cam
    k = 0
    w_idx = 0
    while k < n:
        rng = np.random.default_rng([seed, SPLITS[split], 29, w_idx])
        w_idx += 1
        world = random_world(rng, cfg.world)
        half = cfg.world.size_m / 2 - 8.0
        for _ in range(min(cfg.views_per_world, n - k)):
            app, light = random_appearance(rng, nadir=False)
            T_wb = rover_pose(world, rng.uniform(-half, half, 2), rng.uniform(0, 2 * np.pi))
            sr = Renderer(world, app).stereo(T_wb @ T_base_cam, cam, cfg.stereo.baseline_m, light, rng=rng)
            labels = box_labels(sr.instance_left, cfg.min_area_px, cfg.min_side_px)
            labels = _ignore_far(labels, world, sr.T_world_left, cfg.max_range_m)
            yield Sample(sr.left, labels, stereo=sr, world=world)
            k += 1


def _ignore_far(labels: BoxLabels, world: World, T_world_cam: np.ndarray, max_range_m: float) -> BoxLabels:
    if len(labels.rock) == 0:
        return labels
    rng_m = np.linalg.norm(world.rocks.xyz_m[labels.rock] - T_world_cam[:3, 3], axis=1)
    return replace(labels, ignore=labels.ignore | (rng_m > max_range_m))

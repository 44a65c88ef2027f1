"""Configuration of the kilometre-scale tiled worlds (``SimConfig.tiled``); ``None`` fields take
the preset's value (:mod:`sim.tiled.presets`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sim.craters import EjectaConfig
from sim.errors import SimError


class TiledConfigError(SimError, ValueError):
    """A tiled world's setting is out of range."""


@dataclass(frozen=True)
class TerrainNoiseConfig:
    """Large-scale relief: fractal value noise (:class:`sim.tiled.noise.FractalNoise`)."""

    relief_m: float | None = None  # amplitude of the largest octave
    hurst: float | None = None
    largest_scale_m: float = 512.0
    smallest_scale_m: float = 2.0  # finer roughness comes from rocks and small craters


@dataclass(frozen=True)
class RockFieldConfig:
    """Background rocks: Golombek & Rapp (1997) with abundance ``k`` (:mod:`sim.rock_sfd`)."""

    k: float | None = None
    min_diameter_m: float = 0.1
    max_diameter_m: float = 3.0
    embed_fraction: float = 0.15


@dataclass(frozen=True)
class CraterFieldConfig:
    """Craters: :class:`sim.craters.CraterSFD` of a surface of ``age_gyr``."""

    age_gyr: float | None = None
    production: str = "hartmann2005"
    equilibrium: bool = True
    min_diameter_m: float = 1.0
    max_diameter_m: float = 200.0
    density_scale: float = 1.0


@dataclass(frozen=True)
class KmRouteConfig:
    """Mission-like route: strategic waypoints, local avoidance, stops (:mod:`sim.tiled.route`)."""

    strategic_min_m: float = 150.0  # distance between strategic waypoints
    strategic_max_m: float = 350.0
    heading_sigma_deg: float = 35.0  # spread of the heading change at a strategic waypoint
    max_turn_deg: float = 90.0
    edge_margin_m: float = 60.0
    path_clearance_m: float = 80.0  # strategic legs keep this far from the earlier route
    stop_s: float = 0.0  # extra standstill at each strategic waypoint (optional stops)
    drive_step_m: float = 25.0  # local plans: the rover drives this far, stops, plans again
    cell_m: float = 0.5  # local planning grid
    corridor_m: float = 30.0  # half-width of the local planning window around the leg
    avoid_rock_diameter_m: float = 0.5
    rock_clearance_m: float = 0.4
    avoid_crater_depth_m: float = 0.25  # crater interiors deeper than this are avoided
    crater_clearance_m: float = 0.5
    max_slope_deg: float = 15.0
    revisit_radius_m: float = 20.0  # never back within this of where it was ...
    revisit_after_s: float = 300.0  # ... more than this long ago
    loop: bool = False  # a closed loop back to the start is asked for (no revisit rule at its end)


@dataclass(frozen=True)
class OrbitalProductsConfig:
    """Orbital image, catalogs and their coverage (:mod:`sim.tiled.orbital`). The rock catalog's
    detector is ``sensors.orbital``; the image GSD is ``sensors.orbital.gsd_m``."""

    corridor_m: float = 150.0  # image and catalogs cover the tiles within this of the route
    image_tile_px: int = 512
    sun_elevation_deg: float = 30.0
    sun_azimuth_deg: float = 135.0
    write_image: bool = True
    # the terrain model dem.tif (sim.tiled.dem): a stereo DTM's posts, effective resolution (Gaussian
    # sigma in posts) and vertical error (RMS, correlation length); HiRISE-class values
    write_dem: bool = True
    dem_post_m: float = 1.0
    dem_smoothing_posts: float = 1.0
    dem_sigma_m: float = 0.15
    dem_correlation_m: float = 25.0
    render_min_rock_px: float = 0.5  # rocks smaller than this many pixels are left out of the render
    # crater detector: p = recall_max * sigmoid((ln D_px - ln d50_px) / log_width) * (1 - penalty * g)
    crater_recall_max: float = 0.95
    crater_d50_px: float = 6.0
    crater_log_width: float = 0.25
    crater_degradation_penalty: float = 0.6
    crater_min_px: float = 4.0
    crater_precision: float = 0.9
    crater_sigma_centre_rel: float = 0.05  # centre error sigma / D (plus half a pixel)
    crater_sigma_size_rel: float = 0.05

    def __post_init__(self) -> None:
        for key in ("dem_post_m", "dem_correlation_m"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) > 0):
                raise TiledConfigError(f"tiled.orbital.{key} must be positive and finite, got {getattr(self, key)!r}")
        for key in ("dem_smoothing_posts", "dem_sigma_m"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) >= 0):
                raise TiledConfigError(f"tiled.orbital.{key} must be >= 0 and finite, got {getattr(self, key)!r}")


@dataclass(frozen=True)
class TiledWorldConfig:
    """A kilometre-scale world, generated lazily per tile from (seed, tile index)."""

    size_m: float | None = None  # square world side (None: preset, grown for longer traverses)
    tile_size_m: float = 64.0
    resolution_m: float = 0.25  # fine DEM grid
    tile_margin_m: float = 2.0  # each tile's DEM extends this far beyond it (rock footprints)
    coarse_resolution_m: float = 8.0
    coarse_tile_m: float = 1024.0
    cache_tiles: int = 48  # fine tiles kept in memory (LRU)
    sensor_window_margin_m: float = 12.0  # the stereo scene covers the chunk's path + this
    terrain: TerrainNoiseConfig = field(default_factory=TerrainNoiseConfig)
    rocks: RockFieldConfig = field(default_factory=RockFieldConfig)
    craters: CraterFieldConfig = field(default_factory=CraterFieldConfig)
    ejecta: EjectaConfig = field(default_factory=EjectaConfig)
    route: KmRouteConfig = field(default_factory=KmRouteConfig)
    orbital: OrbitalProductsConfig = field(default_factory=OrbitalProductsConfig)
    chunk_s: float = 600.0  # sensors run on one drive step or stop at a time, split into chunks of at most this

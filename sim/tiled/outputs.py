"""A kilometre-preset ``fgslam sim`` directory, written in one streaming pass:
``bag/`` (written while the rover drives), the orbital products of :mod:`sim.tiled.orbital`,
``world.yaml`` (world, seed, extents, georeference, models, the terrain model ``dem`` with its height
error measured on the driven route against the ground truth, the resolved config, statistics and
the ``backend_overrides`` the back-ends need for this run's stereo errors, the ``relocalizer``
settings sized to its catalog) and ``backend.yaml`` (those two blocks alone, for
``fgslam run/compare --config``)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from reloc.config import config_to_dict
from sim.bag_scene import bag_description
from sim.bag_writer import BagSummary, write_bag
from sim.config import SimConfig
from sim.errors import SimError
from sim.outputs import _plain
from sim.tiled.orbital import OrbitalProducts, write_orbital_products
from sim.tiled.presets import TILED_PRESETS, backend_calibration, relocalizer_calibration
from sim.tiled.stream import TiledSimulation, cpu_s, peak_rss_mb

log = logging.getLogger(__name__)

TRUTH_SPACING_M = 0.1  # the terrain model's height error on the route: a true pose per this much travel


@dataclass
class TiledRun:
    """What :func:`simulate_to_bag` produced: the resolved ``config``, ``stats``, the ``bag``
    summary, the orbital ``products`` and the strategic ``route`` waypoints."""

    config: SimConfig
    stats: dict
    bag: BagSummary
    products: OrbitalProducts
    route: list


def _scene_and_stream(sim: TiledSimulation):
    """The bag's scene (the mast camera's mounting, odometry's start in world) and the
    measurement stream: the stream is read up to its first ground-truth pose for the start (a
    few messages at t = 0), which are then given back first."""
    from itertools import chain

    import numpy as np
    from scipy.spatial.transform import Rotation

    from reloc.measurements import GroundTruthPose
    from sim.bag_scene import BagScene
    from sim.sensors.stereo import StereoCamera

    it = iter(sim.measurements())
    head = []
    T0 = None
    for m in it:
        head.append(m)
        if isinstance(m, GroundTruthPose):
            T0 = np.eye(4)
            T0[:3, :3] = Rotation.from_quat(m.quat_xyzw).as_matrix()
            T0[:3, 3] = m.position_m
            break
    scene = BagScene(T_base_cam=StereoCamera.from_config(sim.config.sensors.stereo).T_base_cam, T_world_odom=T0)
    return scene, chain(head, it)


def _keep_truth(stream, kept: list, spacing_m: float):
    """``stream`` as it is; the base_link positions of its ground-truth poses, one per
    ``spacing_m`` of travel in x, y, appended to ``kept`` as they pass."""
    from reloc.measurements import GroundTruthPose

    last = None
    for m in stream:
        if isinstance(m, GroundTruthPose):
            p = m.position_m
            if last is None or (p[0] - last[0]) ** 2 + (p[1] - last[1]) ** 2 >= spacing_m ** 2:
                kept.append(p)
                last = p
        yield m


def simulate_to_bag(cfg: SimConfig, out: Path, *, overwrite: bool = True,
                    progress: Callable[[str, float, float], None] | None = None,
                    style=None, topics=None,
                    write_products: Callable[[Callable[[], OrbitalProducts]], OrbitalProducts] | None = None,
                    ) -> TiledRun:
    """Simulate the kilometre-preset run ``cfg`` and write its directory ``out`` (see module doc).
    ``progress(stage, done, total)`` is called as it goes (stage "drive" in metres, "catalogs"
    and "image" in tiles). ``style``/``topics``: the bag's :class:`sim.bag_scene.BagStyle` and
    names (default fgslam's: no /tf, stream-second stamps). With ``style.tf`` the bag holds
    ``/tf_static`` (world -> odom at the start, base_link -> the mast camera) and ``/tf`` (world
    -> base_link with every ground-truth pose); the orbital catalog is made after the drive, so
    it is named in the bag's metadata (``fgslam.catalog``: ``catalog.csv``) rather than latched
    as markers. ``write_products(write)``: how the orbital products are written once the bag is
    closed; ``write()`` writes them and returns their summary (default: called at once; the demo
    has it run on a forked process while it reads the bag back)."""
    import yaml

    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimError(f"cannot create output directory {out}: {exc}") from exc
    t0, c0 = time.perf_counter(), cpu_s()
    sim = TiledSimulation(cfg, progress=None if progress is None else
                          (lambda d: progress("drive", d, sim.config.traverse.distance_m)))
    scene, stream = _scene_and_stream(sim)
    truth: list = []
    bag = write_bag(out / "bag", _keep_truth(stream, truth, TRUTH_SPACING_M), overwrite=overwrite, style=style,
                    topics=topics, scene=scene, custom_data={"fgslam.catalog": "catalog.csv"})
    t_drive = time.perf_counter() - t0
    rss_drive = peak_rss_mb()
    def write() -> OrbitalProducts:
        return write_orbital_products(sim.world, sim.driver.planner.history_xy, sim.config, out, progress,
                                      route_xyz=truth)

    products = write() if write_products is None else write_products(write)
    wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    stats = dict(sim.stats)
    stats.update({
        "bag_bytes": bag.n_bytes, "bag_messages": bag.n_messages, "bag_counts": dict(bag.counts),
        "wall_drive_and_bag_s": round(t_drive, 2), "wall_total_s": round(wall, 2),
        "real_time_factor": round(stats["duration_s"] / max(wall, 1e-9), 2),
        "cpu_s": round(cpu, 2),  # all threads: on one core (taskset) the one-core cost
        "real_time_factor_cpu": round(stats["duration_s"] / max(cpu, 1e-9), 2),
        "peak_rss_mb_drive": round(rss_drive, 1), "peak_rss_mb": round(peak_rss_mb(), 1),
        "n_catalog": products.counts.get("catalog", 0), "n_catalog_true": products.counts.get("catalog_true", 0),
        "n_craters_catalog": products.counts.get("craters", 0), "n_craters_true": products.counts.get("craters_true", 0),
        "n_craters_in_coverage": products.counts.get("craters_true_in_coverage", 0),
        "n_rocks_true_written": products.counts.get("rocks_true", 0), "coverage_tiles": products.counts.get("coverage_tiles", 0),
    })
    stats["catalog_precision"] = stats["n_catalog_true"] / max(stats["n_catalog"], 1)
    rc = sim.config
    world = sim.world
    overrides = backend_calibration(rc)
    reloc = relocalizer_calibration(rc)
    doc = {
        "world": rc.world,
        "seed": int(rc.seed),
        "source": "tiled",
        "summary": TILED_PRESETS[rc.world].summary,
        "extent": list(world.extent),
        "orbital_extent": list(products.image_extent) if products.image_extent else list(world.extent),
        "orbital_gsd_m": products.overview_gsd_m,
        "orbital_image": None if products.image_extent is None else {
            "file": "orbital.tif", "world_file": "orbital.tfw", "overview": "orbital.png",
            "gsd_m": rc.sensors.orbital.gsd_m, "extent": list(products.image_extent),
            "width_px": products.image_shape[1], "height_px": products.image_shape[0],
            "tile_px": rc.tiled.orbital.image_tile_px,
            "georeference": "GeoTIFF ModelPixelScale + ModelTiepoint, pixel-is-area: pixel (col, row) covers "
                            "x in xmin + gsd [col, col + 1], y in ymax - gsd [row + 1, row]; user-defined metric "
                            "CRS = the simulator's world frame (x east, y north, metres)",
        },
        "dem": products.dem,
        "rock_model": {"model": "Golombek & Rapp (1997)", "k": rc.tiled.rocks.k, "q": world.rock_model.q,
                       "diameter_m": [rc.tiled.rocks.min_diameter_m, rc.tiled.rocks.max_diameter_m],
                       "density_per_m2": world.rock_model.density_per_m2},
        "crater_model": {"production": rc.tiled.craters.production, "chronology": "Hartmann (2005), Michael (2013) eq. 3",
                         "equilibrium": "Hartmann (1984)" if rc.tiled.craters.equilibrium else None,
                         "age_gyr": rc.tiled.craters.age_gyr,
                         "diameter_m": [rc.tiled.craters.min_diameter_m, rc.tiled.craters.max_diameter_m]},
        "bag": bag_description(style, topics),
        "route": [[round(float(x), 2), round(float(y), 2)] for x, y in sim.driver.route],
        "backend_overrides": overrides,
        "relocalizer": reloc,
        "config": config_to_dict(rc),
        "stats": stats,
    }
    (out / "world.yaml").write_text(yaml.safe_dump(_plain(doc), sort_keys=False))
    (out / "backend.yaml").write_text(yaml.safe_dump(_plain({"backend_overrides": overrides, "relocalizer": reloc}),
                                                       sort_keys=False))
    log.info("wrote %s: %.0f m, bag %.1f MB, %.1f x real time, peak RSS %.0f MB", out, stats["distance_m"],
             bag.n_bytes / 1e6, stats["real_time_factor"], stats["peak_rss_mb"])
    return TiledRun(rc, stats, bag, products, doc["route"])

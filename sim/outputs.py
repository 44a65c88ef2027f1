"""Files of a simulator run: world.yaml (world, seed, every parameter used, stats), rocks_true.csv,
catalog.csv and orbital.png. The bag is written by :mod:`sim.bag_writer`."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from reloc.config import config_to_dict
from reloc.measurements import RockCatalog
from sim.errors import SimError
from sim.orbital_image import orbital_image

log = logging.getLogger(__name__)

ORBITAL_PNG_GSD_M = 0.05


def _plain(value):
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def world_yaml_dict(run, orbital_gsd_m: float = ORBITAL_PNG_GSD_M) -> dict:
    """The content of world.yaml: world name, seed, extent, resolved config, preset and stats."""
    p = run.world.preset
    return _plain({
        "world": run.world.name,
        "seed": int(run.config.seed),
        "source": run.world.source,
        "extent": list(run.world.extent),
        "orbital_extent": list(run.world.extent),
        "orbital_gsd_m": orbital_gsd_m,
        "relief_m": float(np.ptp(run.world.terrain.z_m)),
        "preset": None if p is None else {
            "size_x_m": p.size_x_m, "size_y_m": p.size_y_m, "relief_m": p.relief_m, "n_rocks": p.n_rocks,
            "traverse_m": p.traverse_m, "duration_s": p.duration_s,
        },
        "config": config_to_dict(run.config),
        "stats": run.stats,
    })


def write_rocks_true_csv(path: Path, rocks) -> None:
    """True rocks as CSV ``id,x,y,z,size,height`` (world metres; size = diameter)."""
    data = np.column_stack([rocks.id, rocks.xyz_m, rocks.size_m, rocks.height_m])
    np.savetxt(path, data, delimiter=",", header="id,x,y,z,size,height", comments="",
               fmt=["%d", "%.4f", "%.4f", "%.4f", "%.4f", "%.4f"])


def write_catalog_csv_plain(path: Path, catalog: RockCatalog) -> None:
    """Catalog as CSV ``x,y,size,score`` (the fgslam.io reader's format)."""
    data = np.column_stack([catalog.xy_m, catalog.size_m, catalog.score])
    np.savetxt(path, data, delimiter=",", header="x,y,size,score", comments="", fmt="%.4f")


def write_outputs(run, out_dir: Path, *, catalog: bool = True, orbital_gsd_m: float = ORBITAL_PNG_GSD_M,
                  bag: dict | None = None) -> dict[str, Path]:
    """Write world.yaml, rocks_true.csv, orbital.png (and catalog.csv unless ``catalog`` is False)
    into ``out_dir``; returns the paths by name. ``bag``: how the bag was written
    (:func:`sim.bag_scene.bag_description`), recorded in world.yaml."""
    import cv2
    import yaml

    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimError(f"cannot create output directory {out_dir}: {exc}") from exc
    paths = {name: out_dir / name for name in ("world.yaml", "rocks_true.csv", "orbital.png")}
    doc = world_yaml_dict(run, orbital_gsd_m)
    if bag is not None:
        doc["bag"] = bag
    paths["world.yaml"].write_text(yaml.safe_dump(doc, sort_keys=False))
    write_rocks_true_csv(paths["rocks_true.csv"], run.rocks_true)
    img, _ = orbital_image(run.world, orbital_gsd_m)
    if not cv2.imwrite(str(paths["orbital.png"]), img[:, :, ::-1]):
        raise SimError(f"cannot write {paths['orbital.png']}")
    if catalog:
        paths["catalog.csv"] = out_dir / "catalog.csv"
        write_catalog_csv_plain(paths["catalog.csv"], run.catalog)
    return paths

"""Rerun logging of the crater kind: catalog and mapped craters as rim circles of their diameter
(a crater is a ring on the ground, not a disc), the mapped rim centres with their 3-sigma x/y
discs as for every point landmark (:class:`fgslam.viz.landmarks.PointLandmarkLogger`)."""

from __future__ import annotations

import numpy as np

from fgslam.viz.landmarks import PointLandmarkLogger
from fgslam.viz.rerun_log import Z_CATALOG, Z_LANDMARKS

RIM_SEGMENTS = 32


def rim_strips(xy_m: np.ndarray, diameter_m: np.ndarray, z: float) -> list[np.ndarray]:
    """Closed circles (RIM_SEGMENTS + 1, 3) of ``diameter_m`` (N,) round ``xy_m`` (N, 2) at height ``z``."""
    a = np.linspace(0.0, 2 * np.pi, RIM_SEGMENTS + 1)
    ring = np.column_stack([np.cos(a), np.sin(a)])
    return [np.column_stack([c + 0.5 * d * ring, np.full(len(a), z)]) for c, d in zip(np.reshape(xy_m, (-1, 2)),
                                                                                  np.reshape(diameter_m, (-1,)))]


class CraterLogger(PointLandmarkLogger):
    """Rim circles of the catalog and of the map (see module doc)."""

    def log_catalog(self, rec, entity: str, catalog) -> None:
        import rerun as rr

        rec.log(entity, rr.LineStrips3D(rim_strips(catalog.xy_m, catalog.size_m, Z_CATALOG), colors=self.catalog_color),
                static=True)

    def log_map(self, rec, entity: str, lmap, color) -> None:
        import rerun as rr

        if not len(lmap):
            return
        super().log_map(rec, entity, lmap, color)
        rec.log(f"{entity}/rims", rr.LineStrips3D(rim_strips(lmap.xyz_world_m[:, :2], lmap.size_m, Z_LANDMARKS),
                                                  colors=color), static=True)

"""Rerun logging of a landmark kind: the default layer (``LandmarkKind.rerun``), used by rocks.

A kind's rerun layer is a class built as ``cls(kind_name)`` with ``log_catalog(rec, entity,
catalog)`` (static: the orbital catalog, ``catalog.xy_m`` (N, 2) and ``catalog.size_m`` (N,)) and
``log_map(rec, entity, lmap, color)`` (static: a run's final :class:`reloc.backend.LandmarkMap`).
This one draws catalog entries as discs of their diameter and map landmarks as discs of their
3-sigma radius (the larger axis of the x/y covariance), on the flat map of
:mod:`fgslam.viz.rerun_log`.
"""

from __future__ import annotations

import numpy as np

from fgslam.viz.rerun_log import COLORS, Z_CATALOG, Z_LANDMARKS, flat


class PointLandmarkLogger:
    """Catalog discs and map 3-sigma discs of one kind (see module doc)."""

    catalog_color = COLORS["catalog"]

    def __init__(self, kind: str) -> None:
        self.kind = kind

    def log_catalog(self, rec, entity: str, catalog) -> None:
        import rerun as rr

        rec.log(entity, rr.Points3D(flat(catalog.xy_m, Z_CATALOG), radii=0.5 * np.asarray(catalog.size_m),
                                    colors=self.catalog_color), static=True)

    def log_map(self, rec, entity: str, lmap, color) -> None:
        import rerun as rr

        if not len(lmap):
            return
        rec.log(entity, rr.Points3D(flat(lmap.xyz_world_m[:, :2], Z_LANDMARKS), radii=three_sigma_radius(lmap.cov_world_m2),
                                    colors=color), static=True)


def three_sigma_radius(cov_world_m2: np.ndarray) -> np.ndarray:
    """Radius (N,) of the disc a map landmark is drawn as: 3 sigma along the major axis of its x/y
    covariance (N, 3, 3) or (N, 2, 2). A disc costs a recording 16 bytes a landmark where an
    ellipse costs 40: a kilometre of smoother map holds ~27 000 rocks (docs/app.md)."""
    c = np.asarray(cov_world_m2, dtype=float)[:, :2, :2]
    w = np.linalg.eigvalsh(0.5 * (c + np.swapaxes(c, 1, 2)))
    return 3.0 * np.sqrt(np.clip(w[:, -1], 0.0, None))

"""Rerun logging of a landmark kind: the default layer (``LandmarkKind.rerun``), used by rocks.

A kind's rerun layer is a class built as ``cls(kind_name)`` with ``log_catalog(rec, entity,
catalog)`` (static: the orbital catalog, ``catalog.xy_m`` (N, 2) and ``catalog.size_m`` (N,)) and
``log_map(rec, entity, lmap, color)`` (static: a run's final :class:`reloc.backend.LandmarkMap`).
This one draws catalog entries as discs of their diameter and map landmarks as their 3-sigma
x/y ellipses, on the flat map of :mod:`fgslam.viz.rerun_log`.
"""

from __future__ import annotations

import numpy as np

from fgslam.viz.rerun_log import COLORS, Z_CATALOG, Z_LANDMARKS, ellipses, flat


class PointLandmarkLogger:
    """Catalog discs and map ellipses of one kind (see module doc)."""

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
        half, q = ellipses(lmap.cov_world_m2[:, :2, :2])
        rec.log(entity, rr.Ellipsoids3D(centers=flat(lmap.xyz_world_m[:, :2], Z_LANDMARKS), half_sizes=half,
                                        quaternions=q, colors=color, fill_mode="solid"), static=True)

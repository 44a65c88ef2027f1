"""The cairn kind's rerun layer (toy kind): catalog and map as points."""

from __future__ import annotations

import numpy as np

from fgslam.viz.rerun_log import Z_CATALOG, Z_LANDMARKS, flat


class CairnLogger:
    def __init__(self, kind: str) -> None:
        self.kind = kind

    def log_catalog(self, rec, entity: str, catalog) -> None:
        import rerun as rr

        rec.log(entity, rr.Points3D(flat(catalog.xy_m, Z_CATALOG), radii=0.3, colors=(120, 120, 255)), static=True)

    def log_map(self, rec, entity: str, lmap, color) -> None:
        import rerun as rr

        if len(lmap):
            rec.log(entity, rr.Points3D(flat(lmap.xyz_world_m[:, :2], Z_LANDMARKS), radii=np.full(len(lmap), 0.2),
                                        colors=color), static=True)

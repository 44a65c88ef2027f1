"""Nadir detections (rocks or craters) -> a world-frame catalog."""

from __future__ import annotations

import numpy as np

from reloc.detector.boxes import Detections
from reloc.detector.circles import CraterDetections
from reloc.measurements import RockCatalog


def catalog_from_detections(dets: Detections | CraterDetections, gsd_m: float,
                            origin_xy_m: tuple[float, float] = (0.0, 0.0)) -> RockCatalog:
    """Catalog (world metres; the ``x,y,size,score`` table, whatever the landmark kind) from
    nadir ``dets``: pixel (u, v) -> (x0 + u gsd, y0 - v gsd), with ``origin_xy_m`` = (x0, y0) the
    world position of the image's top-left corner (row 0 is the +y edge, column 0 the -x edge);
    size = mean box side (rocks) or rim diameter (craters) x gsd; score = detector score."""
    if not gsd_m > 0:
        from reloc.detector.runtime import DetectorError

        raise DetectorError(f"ground sample distance must be > 0 m/px, got {gsd_m}")
    c = dets.centers_px
    xy = np.column_stack([origin_xy_m[0] + c[:, 0] * gsd_m, origin_xy_m[1] - c[:, 1] * gsd_m])
    sizes = np.asarray(dets.sizes_px, dtype=float)
    sizes = sizes.mean(axis=1) if sizes.ndim == 2 else sizes
    size = np.maximum(sizes * gsd_m, 1e-3) if len(dets) else np.zeros(0)
    return RockCatalog(xy.reshape(-1, 2), size, dets.score.astype(float))

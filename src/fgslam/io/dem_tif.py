"""Orbital terrain models as GeoTIFF: one band of heights (metres, world frame), georeferenced by
ModelPixelScale (33550) and ModelTiepoint (33922) as the orbital image is (pixel-is-area: the
upper-left corner of pixel (0, 0) at the tie point), no-data as NaN or as the GDAL_NODATA
value (42113). What ``fgslam sim`` writes as ``dem.tif`` on the orbital-scale worlds; a real
DTM (HiRISE, CTX) exported in the world frame of the run reads the same way."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fgslam.errors import InputFileError
from reloc.dem import Dem, DemError

TAG_PIXEL_SCALE, TAG_TIEPOINT, TAG_NODATA = 33550, 33922, 42113


def read_dem(path: str | Path) -> Dem:
    """Read a DEM GeoTIFF into a :class:`reloc.dem.Dem`; anything malformed is an
    :class:`InputFileError` naming the file and the problem."""
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: DEM not found")
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            tags = {t.code: t.value for t in page.tags.values()}
            z = page.asarray()
    except (tifffile.TiffFileError, OSError, ValueError, IndexError) as exc:
        raise InputFileError(f"{path}: not a readable GeoTIFF ({exc})") from exc
    if z.ndim != 2:
        raise InputFileError(f"{path}: a DEM has one band of heights, this image has shape {z.shape}")
    if not np.issubdtype(z.dtype, np.floating) and not np.issubdtype(z.dtype, np.integer):
        raise InputFileError(f"{path}: heights of type {z.dtype} (expected float or integer)")
    scale, tie = tags.get(TAG_PIXEL_SCALE), tags.get(TAG_TIEPOINT)
    if scale is None or tie is None or len(scale) < 2 or len(tie) < 6:
        raise InputFileError(f"{path}: no georeference (ModelPixelScale and ModelTiepoint tags are needed)")
    sx, sy = float(scale[0]), float(scale[1])
    if not (math.isfinite(sx) and sx > 0 and abs(sx - sy) <= 1e-9 * sx):
        raise InputFileError(f"{path}: posts must be square and positive, ModelPixelScale is {tuple(scale[:2])}")
    i0, j0, x0, y0 = float(tie[0]), float(tie[1]), float(tie[3]), float(tie[4])
    z = z.astype(float)
    nodata = tags.get(TAG_NODATA)
    if nodata is not None:
        try:
            nd = float(str(nodata).strip().strip("\x00"))
        except ValueError:
            raise InputFileError(f"{path}: GDAL_NODATA {nodata!r} is not a number") from None
        if not math.isnan(nd):
            z[z == nd] = np.nan
    try:
        return Dem(z, sx, x0 - i0 * sx, y0 + j0 * sx)
    except DemError as exc:
        raise InputFileError(f"{path}: {exc}") from None

"""An orbital terrain model (DEM) as the estimators use it: heights on a regular grid of posts in
the world frame, sampled bilinearly with the gradient of the cell (no I/O here; the GeoTIFF
reader is :func:`fgslam.io.dem_tif.read_dem`).

Grid convention (GeoTIFF pixel-is-area, as the orbital image): ``z_m[i, j]`` is the height at
the post centre ``x = xmin + (j + 0.5) post``, ``y = ymax - (i + 0.5) post`` (row 0 at the
north edge); NaN where the model has no data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reloc.errors import RelocError


class DemError(RelocError, ValueError):
    """A terrain model is malformed (shape, post, extent, no finite height)."""


@dataclass(frozen=True)
class DemSample:
    """The model at one point: height ``z_m`` and its slope ``grad`` (2,) (dz/dx, dz/dy)."""

    z_m: float
    grad: np.ndarray


@dataclass(frozen=True)
class Dem:
    """Heights ``z_m`` (H, W) on posts ``post_m`` apart; ``xmin``/``ymax`` the grid's north-west
    corner (see the module doc)."""

    z_m: np.ndarray
    post_m: float
    xmin: float
    ymax: float

    def __post_init__(self) -> None:
        z = np.asarray(self.z_m, dtype=float)
        if z.ndim != 2 or min(z.shape) < 2:
            raise DemError(f"a DEM needs a 2D grid of at least 2 x 2 posts, got shape {z.shape}")
        if not (math.isfinite(self.post_m) and self.post_m > 0):
            raise DemError(f"the DEM's post spacing must be positive and finite, got {self.post_m!r}")
        if not (math.isfinite(self.xmin) and math.isfinite(self.ymax)):
            raise DemError(f"the DEM's corner must be finite, got ({self.xmin!r}, {self.ymax!r})")
        if np.any(np.isinf(z)):
            raise DemError("the DEM holds infinite heights (no-data must be NaN)")
        if not np.any(np.isfinite(z)):
            raise DemError("the DEM holds no finite height")
        if z.flags.writeable or z.base is not None:  # the caller's array (or a view of one): a frozen copy
            z = z.copy()
            z.setflags(write=False)
        object.__setattr__(self, "z_m", z)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid's outer edges."""
        h, w = self.z_m.shape
        return (self.xmin, self.xmin + w * self.post_m, self.ymax - h * self.post_m, self.ymax)

    def sample(self, x: float, y: float) -> DemSample | None:
        """Bilinear height and the cell's gradient at (x, y); None outside the post centres or
        where a post of the cell has no data."""
        h, w = self.z_m.shape
        u = (x - self.xmin) / self.post_m - 0.5  # column coordinate of the post centres
        v = (self.ymax - y) / self.post_m - 0.5  # row coordinate (down = south)
        if not (0.0 <= u <= w - 1 and 0.0 <= v <= h - 1):
            return None
        j, i = min(int(u), w - 2), min(int(v), h - 2)
        fu, fv = u - j, v - i
        z00, z01 = self.z_m[i, j], self.z_m[i, j + 1]
        z10, z11 = self.z_m[i + 1, j], self.z_m[i + 1, j + 1]
        if not (math.isfinite(z00) and math.isfinite(z01) and math.isfinite(z10) and math.isfinite(z11)):
            return None
        top, bottom = z00 + fu * (z01 - z00), z10 + fu * (z11 - z10)
        z = top + fv * (bottom - top)
        dz_du = (1.0 - fv) * (z01 - z00) + fv * (z11 - z10)
        dz_dv = bottom - top
        return DemSample(float(z), np.array([dz_du / self.post_m, -dz_dv / self.post_m]))

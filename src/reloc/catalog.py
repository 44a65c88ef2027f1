"""The rock catalog and its triangle index, built once per catalog.

``Catalog(xy, size)`` holds the orbital rocks (world frame, metres), a KD-tree over them (for
inlier scoring and local density) and the geometric hash of every non-degenerate triangle formed
by a rock and each pair of its ``neighbours`` nearest rocks. Triangles are stored compactly:
int32 vertex ids in canonical label order and float32 sorted sides.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from reloc.descriptors import label_triangles
from reloc.errors import RelocError
from reloc.hashing import TriangleHash
from reloc.sampling import knn_triangles, map_chunks

__all__ = ["Catalog", "CatalogConfig", "CatalogError"]

log = logging.getLogger(__name__)


class CatalogError(RelocError, ValueError):
    """The catalog arrays are unusable (shape, NaN, non-positive sizes, too few rocks)."""


@dataclass(frozen=True, slots=True)
class CatalogConfig:
    """Index parameters. ``neighbours``: k of the k-nearest pairs per anchor rock;
    ``bin_m``: hash bin width on each side length; ``min_side_m``/``min_shape``: degeneracy
    limits (near-duplicate rocks / near-collinear triangles, normalised area in [0, 1]);
    ``workers``: threads for the build's KD-tree queries and labelling (-1: all cores; the index
    is the same)."""

    neighbours: int = 6
    bin_m: float = 0.08
    min_side_m: float = 0.25
    min_shape: float = 0.12
    workers: int = -1

    def __post_init__(self) -> None:
        if self.neighbours < 2:
            raise CatalogError(f"CatalogConfig.neighbours must be >= 2, got {self.neighbours}")
        if not (self.bin_m > 0 and self.min_side_m >= 0 and 0 <= self.min_shape < 1):
            raise CatalogError(f"invalid CatalogConfig {self}")


class Catalog:
    """Catalog rocks ``xy`` (N, 2) world metres, diameters ``size`` (N,) metres, and their index.

    Attributes after construction: ``tree`` (cKDTree), ``tri_vertices`` (T, 3) int32,
    ``tri_sides_m`` (T, 3) float32, ``tri_size_q`` (T, 3) uint8 (log diameters quantised with
    ``size_q_lo``/``size_q_step``), all in hash order, ``hash``
    (:class:`~reloc.hashing.TriangleHash`, triangle id = row),
    ``build_time_s``, ``nbytes``, ``density_per_m2`` (rocks per m^2 over the bounding box).
    """

    def __init__(self, xy: np.ndarray, size: np.ndarray, config: CatalogConfig | None = None) -> None:
        self.config = config if config is not None else CatalogConfig()
        t0 = time.perf_counter()
        xy = np.asarray(xy, dtype=float)
        size = np.asarray(size, dtype=float)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise CatalogError(f"catalog xy must have shape (N, 2), got {xy.shape}")
        if size.shape != (xy.shape[0],):
            raise CatalogError(f"catalog size must have shape ({xy.shape[0]},), got {size.shape}")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(size))):
            raise CatalogError("catalog xy/size contain NaN or infinite values")
        if np.any(size <= 0):
            raise CatalogError("catalog size (rock diameter) must be positive")
        if xy.shape[0] < 3:
            raise CatalogError(f"catalog needs at least 3 rocks, got {xy.shape[0]}")
        self.xy = xy
        self.size = size
        self.log_size = np.log(size).astype(np.float32)
        self.tree = cKDTree(xy, balanced_tree=False)  # sliding midpoint: faster to build, as fast to query
        tri = knn_triangles(xy, self.config.neighbours, tree=self.tree, workers=self.config.workers)
        sides, verts, hand = self._label_chunked(tri)
        del tri
        self.hash, order = TriangleHash.build(sides, hand, self.config.bin_m)
        del hand
        # rows in hash order: the runs a query touches are contiguous in every per-triangle array
        self.tri_sides_m = np.take(sides, order, axis=0)
        del sides
        self.tri_vertices = np.take(verts, order, axis=0)
        del verts, order
        # quantised log sizes of each triangle's vertices (label order): a size check before
        # the sides are even read
        ls = self.log_size.astype(float)
        self.size_q_lo = float(ls.min())
        self.size_q_step = max(float(np.ptp(ls)) / 255.0, 1e-3)
        size_q = np.clip(np.round((ls - self.size_q_lo) / self.size_q_step), 0, 255).astype(np.uint8)
        self.tri_size_q = np.take(size_q, self.tri_vertices)
        span = np.ptp(xy, axis=0)
        area = float(max(span[0], 1e-9) * max(span[1], 1e-9))
        self.density_per_m2 = xy.shape[0] / area
        self.build_time_s = time.perf_counter() - t0
        log.info(
            "catalog: %d rocks, %d triangles, %.1f MB index, built in %.2f s",
            len(self), self.n_triangles, self.nbytes / 1e6, self.build_time_s,
        )

    def _label_chunked(
        self, tri: np.ndarray, chunk: int = 1_000_000
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Label triangles in chunks (bounded temporaries); keep the non-degenerate ones compactly."""
        # float32 positions relative to the catalog's corner: mm precision over tens of km,
        # half the memory traffic of the gathers
        xy32 = (self.xy - self.xy.min(axis=0)).astype(np.float32)

        def label(start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            lab = label_triangles(
                xy32,
                tri[start : start + chunk],
                min_side_m=self.config.min_side_m,
                min_shape=self.config.min_shape,
            )
            return (
                lab.sides_m[lab.keep].astype(np.float32, copy=False),
                lab.vertices[lab.keep].astype(np.int32, copy=False),
                lab.handedness[lab.keep],
            )

        parts = map_chunks(label, range(0, tri.shape[0], chunk), self.config.workers)
        sides, verts, hand = ([p[i] for p in parts] for i in range(3))
        if not sides:
            return np.empty((0, 3), np.float32), np.empty((0, 3), np.int32), np.empty(0, np.int8)
        return np.concatenate(sides), np.concatenate(verts), np.concatenate(hand)

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def n_triangles(self) -> int:
        """Number of indexed (non-degenerate) triangles."""
        return int(self.tri_vertices.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the triangle index (hash keys, vertices, sides, size codes; not the KD-tree)."""
        return int(
            self.hash.nbytes + self.tri_size_q.nbytes + self.tri_vertices.nbytes + self.tri_sides_m.nbytes
        )

    def density_near(self, center_xy: np.ndarray, radius_m: float) -> float:
        """Rocks per m^2 within ``radius_m`` of ``center_xy`` (2,) (falls back to the global density)."""
        n = len(self.tree.query_ball_point(np.asarray(center_xy, float), r=radius_m))
        local = n / (np.pi * radius_m * radius_m)
        return float(max(local, 1e-12)) if n >= 3 else float(self.density_per_m2)

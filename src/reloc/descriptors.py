"""Triangle descriptors: a canonical vertex labelling and invariants of a rock triangle.

A triangle of rocks is labelled so that vertex 0 faces the shortest side ``a``, vertex 1 the middle
side ``b`` and vertex 2 the longest side ``c``. Two triangles that are the same up to rotation,
translation and vertex order then have the same sorted sides and corresponding labels, so a match
of descriptors is also a match of vertices. The descriptor adds what a rotation cannot change:

- side-length ratios ``a/c``, ``b/c`` (scale invariant),
- internal angles at vertices 0, 1, 2 (scale invariant, sum to pi),
- normalised area ``4 sqrt(3) A / (a^2 + b^2 + c^2)`` (1 for an equilateral, 0 when collinear),
- handedness: the sign of the signed area of (v0, v1, v2). A mirror image flips it, so mirrored
  constellations never share a hash key.

Degenerate triangles (a side shorter than ``min_side_m``: near-duplicate rocks; normalised area
below ``min_shape``: near-collinear) carry no usable orientation and are excluded.
All functions are vectorised over T triangles; positions in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LabelledTriangles", "TriangleInvariants", "label_triangles", "triangle_invariants"]

_SQRT3_4 = 4.0 * np.sqrt(3.0)


@dataclass(frozen=True, slots=True)
class LabelledTriangles:
    """Canonically labelled triangles: ``vertices`` (T, 3) point indices (vertex i faces side i),
    ``sides_m`` (T, 3) sorted side lengths a <= b <= c, ``handedness`` (T,) +1 (counter-clockwise)
    or -1, ``keep`` (T,) bool: False for degenerate triangles."""

    vertices: np.ndarray
    sides_m: np.ndarray
    handedness: np.ndarray
    keep: np.ndarray


@dataclass(frozen=True, slots=True)
class TriangleInvariants:
    """Rotation/scale/permutation-invariant description of T labelled triangles:
    ``ratios`` (T, 2) = (a/c, b/c), ``angles_rad`` (T, 3) at vertices 0..2, ``norm_area`` (T,),
    ``handedness`` (T,) in {-1, +1}."""

    ratios: np.ndarray
    angles_rad: np.ndarray
    norm_area: np.ndarray
    handedness: np.ndarray


# (s0 > s1, s0 > s2, s1 > s2) -> the vertex order that sorts the sides ascending (ties keep the
# earlier vertex first), and whether that order is an odd permutation (it flips the orientation)
_ORDER = np.zeros((8, 3), np.int64)
_ODD = np.zeros(8, bool)
for _code in range(8):
    _gt = {(0, 1): bool(_code & 4), (0, 2): bool(_code & 2), (1, 2): bool(_code & 1)}
    # rank of side i: how many sides it exceeds (ties: the later one is the larger)
    _rank = [
        sum(_gt[(i, j)] if i < j else not _gt[(j, i)] for j in range(3) if j != i) for i in range(3)
    ]
    if sorted(_rank) == [0, 1, 2]:  # two of the eight codes are cyclic and cannot occur
        _ORDER[_code] = np.argsort(_rank)
        _ODD[_code] = np.linalg.det(np.eye(3)[_ORDER[_code]]) < 0
del _code, _gt, _rank


def label_triangles(
    xy_m: np.ndarray, tri: np.ndarray, *, min_side_m: float = 0.0, min_shape: float = 0.0
) -> LabelledTriangles:
    """Label triangles ``tri`` (T, 3) of points ``xy_m`` (N, 2) canonically; see module doc.

    Works on squared sides (same order, no square root until the end) and picks the sorting
    permutation from a table of the three side comparisons, in the dtype of ``xy_m``."""
    tri = np.asarray(tri)
    p0, p1, p2 = (np.take(xy_m, tri[:, i], axis=0) for i in range(3))
    d21, d02, d10 = p2 - p1, p0 - p2, p1 - p0
    del p0, p1, p2
    # squared side i is the one opposite vertex i
    q = np.empty((tri.shape[0], 3), d21.dtype)
    for i, d in enumerate((d21, d02, d10)):
        np.multiply(d[:, 0], d[:, 0], out=q[:, i])
        q[:, i] += d[:, 1] * d[:, 1]
    cross = d10[:, 1] * d02[:, 0] - d10[:, 0] * d02[:, 1]  # (p1 - p0) x (p2 - p0)
    del d21, d02, d10
    code = (q[:, 0] > q[:, 1]).astype(np.int8) * 4
    code += (q[:, 0] > q[:, 2]).astype(np.int8) * 2
    code += q[:, 1] > q[:, 2]
    order = _ORDER[code]
    vertices = np.take_along_axis(tri, order, axis=1)
    q = np.take_along_axis(q, order, axis=1)
    del order
    handedness = np.where((cross >= 0.0) ^ _ODD[code], 1, -1).astype(np.int8)
    sumsq = q.sum(axis=1)
    area2 = np.abs(cross)  # twice the area
    # normalised area 4 sqrt(3) A / sum(s^2) >= min_shape, without the division
    keep = (q[:, 0] >= min_side_m * min_side_m) & (q[:, 0] > 0.0)
    keep &= _SQRT3_4 * 0.5 * area2 >= min_shape * sumsq
    return LabelledTriangles(vertices, np.sqrt(q), handedness, keep)


def triangle_invariants(p_xy: np.ndarray) -> TriangleInvariants:
    """Invariants of triangles given as vertex positions ``p_xy`` (T, 3, 2) in any vertex order."""
    p = np.asarray(p_xy, dtype=float).reshape(-1, 3, 2)
    lab = label_triangles(p.reshape(-1, 2), np.arange(p.shape[0] * 3).reshape(-1, 3))
    a, b, c = lab.sides_m.T
    with np.errstate(invalid="ignore", divide="ignore"):
        ratios = np.stack([a / c, b / c], axis=1)
        # law of cosines: the angle at vertex i faces side i
        cos0 = (b * b + c * c - a * a) / (2.0 * b * c)
        cos1 = (a * a + c * c - b * b) / (2.0 * a * c)
    ang0 = np.arccos(np.clip(cos0, -1.0, 1.0))
    ang1 = np.arccos(np.clip(cos1, -1.0, 1.0))
    angles = np.stack([ang0, ang1, np.pi - ang0 - ang1], axis=1)
    pts = p.reshape(-1, 2)[lab.vertices]
    cross = (pts[:, 1, 0] - pts[:, 0, 0]) * (pts[:, 2, 1] - pts[:, 0, 1]) - (
        pts[:, 1, 1] - pts[:, 0, 1]
    ) * (pts[:, 2, 0] - pts[:, 0, 0])
    sumsq = np.sum(lab.sides_m**2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        norm_area = np.where(sumsq > 0, _SQRT3_4 * 0.5 * np.abs(cross) / sumsq, 0.0)
    return TriangleInvariants(ratios, angles, norm_area, lab.handedness)

"""Pose hypotheses from triangle correspondences: hash look-up, size check, Procrustes, voting.

For a batch of local triangles this module returns every catalog triangle that agrees with one of
them (sides within tolerance, same handedness, rock sizes within tolerance) together with the 2D
similarity that maps the local triangle onto it (scale within tolerance of 1). Hypotheses are then
binned by (heading, position of the local map's centroid): the true pose collects one vote from
every local triangle that exists in the catalog, a wrong one rarely more than one or two, so the
most-voted bins are verified first.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations

import numpy as np

from reloc.catalog import Catalog
from reloc.hashing import expand_runs
from reloc.procrustes import similarity_batch

__all__ = ["Hypotheses", "LocalTriangles", "generate_hypotheses", "pose_bins"]

# the 6 relabellings of a triangle and whether each reverses its orientation
_PERMS = np.array(list(permutations(range(3))), dtype=np.int64)
_ODD = np.array([np.linalg.det(np.eye(3)[list(p)]) < 0 for p in _PERMS])


@dataclass(frozen=True, slots=True)
class LocalTriangles:
    """Labelled local triangles: ``vertices`` (T, 3), ``sides_m`` (T, 3) sorted, ``handedness`` (T,)."""

    vertices: np.ndarray
    sides_m: np.ndarray
    handedness: np.ndarray

    def __len__(self) -> int:
        return int(self.vertices.shape[0])

    def take(self, idx: np.ndarray) -> LocalTriangles:
        return LocalTriangles(self.vertices[idx], self.sides_m[idx], self.handedness[idx])


@dataclass(frozen=True, slots=True)
class Hypotheses:
    """H candidate poses ``world = scale R(theta) local + t``: ``theta_rad`` (H,), ``scale`` (H,),
    ``translation`` (H, 2), the correspondence ``local_vertices``/``catalog_vertices`` (H, 3) and
    ``span_m`` (H,), the longest side of the local triangle (longer: better-conditioned pose)."""

    theta_rad: np.ndarray
    scale: np.ndarray
    translation: np.ndarray
    local_vertices: np.ndarray
    catalog_vertices: np.ndarray
    span_m: np.ndarray

    def __len__(self) -> int:
        return int(self.theta_rad.size)


def relabel_variants(
    tri: LocalTriangles, tol_m: np.ndarray
) -> tuple[LocalTriangles, np.ndarray, np.ndarray]:
    """All vertex relabellings that noise within ``tol_m`` (T,) could produce in the other map.

    Near-isosceles triangles can have their two near-equal sides swapped by noise, which swaps two
    labels and flips the handedness; each such variant is queried too. Returns the variants and,
    per variant, the (3,) side lengths in its own label order (the exact-tolerance reference).
    """
    s = tri.sides_m[:, _PERMS]  # (T, 6, 3)
    t = tol_m[:, None]
    ok = (s[:, :, 0] <= s[:, :, 1] + 2 * t) & (s[:, :, 1] <= s[:, :, 2] + 2 * t)
    ti, pi = np.nonzero(ok)
    verts = tri.vertices[ti[:, None], _PERMS[pi]]
    hand = np.where(_ODD[pi], -tri.handedness[ti], tri.handedness[ti]).astype(np.int8)
    return LocalTriangles(verts, tri.sides_m[ti], hand), s[ti, pi], ti


def generate_hypotheses(
    catalog: Catalog,
    local_xy: np.ndarray,
    local_log_size: np.ndarray | None,
    tri: LocalTriangles,
    *,
    side_tol_m: float,
    scale_tol: float,
    size_log_tol: float | None,
    inner_tol_m: float | None = None,
    chunk_candidates: int = 1 << 21,
) -> Hypotheses:
    """Candidate poses for local triangles ``tri`` against ``catalog``; see module doc.
    ``inner_tol_m``: leave out the candidates a call with ``side_tol_m=inner_tol_m`` returns
    (a wider second pass then adds only new hypotheses). Hash candidates are processed in chunks
    of about ``chunk_candidates`` (bounded memory)."""
    tol = side_tol_m + scale_tol * tri.sides_m[:, 2]
    var, var_sides, src = relabel_variants(tri, tol)
    var_tol = tol[src]
    var_inner = None
    if inner_tol_m is not None:
        inner = inner_tol_m + scale_tol * tri.sides_m[:, 2]
        # a variant that the inner pass did not query keeps all its candidates
        s_, t_ = var_sides, 2.0 * inner[src]
        queried = (s_[:, 0] <= s_[:, 1] + t_) & (s_[:, 1] <= s_[:, 2] + t_)
        var_inner = np.where(queried, inner[src], -1.0)
    if len(var) == 0:
        return _empty()
    sized = size_log_tol is not None and local_log_size is not None
    size_lo = size_hi = None
    if sized:
        # quantised size window of every variant vertex: a superset of the exact check below
        loc_q = (np.asarray(local_log_size, float) - catalog.size_q_lo) / catalog.size_q_step
        tol_q = size_log_tol / catalog.size_q_step
        size_lo = np.clip(np.floor(loc_q - tol_q) - 1, 0, 255).astype(np.uint8)[var.vertices]
        size_hi = np.clip(np.ceil(loc_q + tol_q) + 1, 0, 255).astype(np.uint8)[var.vertices]
    run_q, run_start, run_n = catalog.hash.runs(var.sides_m, var.handedness, var_tol)
    cuts = np.arange(chunk_candidates, int(run_n.sum()), chunk_candidates)
    bounds = np.searchsorted(np.cumsum(run_n), cuts)
    parts = []
    for sl in np.split(np.arange(run_n.size), np.unique(bounds)):
        qi, pos = expand_runs(run_q[sl], run_start[sl], run_n[sl])
        if qi.size == 0:
            continue
        if sized:
            cq = np.take(catalog.tri_size_q, pos, axis=0)
            lo, hi = np.take(size_lo, qi, axis=0), np.take(size_hi, qi, axis=0)
            ok = (cq[:, 0] >= lo[:, 0]) & (cq[:, 0] <= hi[:, 0]) & (cq[:, 1] >= lo[:, 1])
            ok &= (cq[:, 1] <= hi[:, 1]) & (cq[:, 2] >= lo[:, 2]) & (cq[:, 2] <= hi[:, 2])
            qi, pos = qi[ok], pos[ok]
        # np.take and per-column comparisons: several times faster than fancy indexing + np.all
        cat_sides = np.take(catalog.tri_sides_m, pos, axis=0)
        ref = np.take(var_sides, qi, axis=0)
        vt = np.take(var_tol, qi)
        d = np.abs(cat_sides - ref)
        ok = (d[:, 0] <= vt) & (d[:, 1] <= vt) & (d[:, 2] <= vt)
        if var_inner is not None:
            it = np.take(var_inner, qi)
            ok &= ~((d[:, 0] <= it) & (d[:, 1] <= it) & (d[:, 2] <= it))
        parts.append((qi[ok], pos[ok]))
    if not parts:
        return _empty()
    qi = np.concatenate([q for q, _ in parts])
    cat_v = np.take(catalog.tri_vertices, np.concatenate([p for _, p in parts]), axis=0)
    loc_v = np.take(var.vertices, qi, axis=0)
    if sized:
        d = np.abs(np.take(catalog.log_size, cat_v) - np.take(local_log_size, loc_v))
        ok = (d[:, 0] <= size_log_tol) & (d[:, 1] <= size_log_tol) & (d[:, 2] <= size_log_tol)
        cat_v, loc_v, qi = cat_v[ok], loc_v[ok], qi[ok]
    if cat_v.shape[0] == 0:
        return _empty()
    theta, scale, t = similarity_batch(np.take(local_xy, loc_v, axis=0), np.take(catalog.xy, cat_v, axis=0))
    # a 3-point fit's scale error is about (side noise) / (side length)
    ok = np.abs(scale - 1.0) <= scale_tol + side_tol_m / np.take(var.sides_m[:, 2], qi)
    span = np.take(var.sides_m[:, 2], qi)
    return Hypotheses(theta[ok], scale[ok], t[ok], loc_v[ok], cat_v[ok].astype(np.int64), span[ok])


def _empty() -> Hypotheses:
    z = np.empty(0)
    zi = np.empty((0, 3), np.int64)
    return Hypotheses(z, z, np.empty((0, 2)), zi, zi, z)


def pose_bins(h: Hypotheses, center_local: np.ndarray, theta_bin_rad: float, xy_bin_m: float) -> np.ndarray:
    """int64 bin key per hypothesis of (heading, world position of ``center_local`` (2,))."""
    c, s = np.cos(h.theta_rad), np.sin(h.theta_rad)
    cx = h.scale * (c * center_local[0] - s * center_local[1]) + h.translation[:, 0]
    cy = h.scale * (s * center_local[0] + c * center_local[1]) + h.translation[:, 1]
    n_theta = max(1, round(2 * np.pi / theta_bin_rad))
    it = np.floor(np.mod(h.theta_rad, 2 * np.pi) / (2 * np.pi) * n_theta).astype(np.int64) % n_theta
    off = np.int64(1 << 20)
    ix = np.clip(np.floor(cx / xy_bin_m).astype(np.int64) + off, 0, 2 * off - 1)
    iy = np.clip(np.floor(cy / xy_bin_m).astype(np.int64) + off, 0, 2 * off - 1)
    return (it * (2 * off) + ix) * (2 * off) + iy

"""Crater detections: the :class:`CraterDetections` result type, disc IoU and greedy
non-maximum suppression of circles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CraterDetections:
    """Craters found in one image: ``centers_px`` (N, 2) (u, v) in the image's pixels (pixel
    edges at integers, so the first pixel's centre is (0.5, 0.5)), ``diameters_px`` (N,) rim
    diameters, ``score`` (N,) in [0, 1]."""

    centers_px: np.ndarray
    diameters_px: np.ndarray
    score: np.ndarray

    @staticmethod
    def empty() -> CraterDetections:
        return CraterDetections(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32))

    def __len__(self) -> int:
        return int(self.score.shape[0])

    @property
    def sizes_px(self) -> np.ndarray:
        """Rim diameters (N,) px (the size a catalog records)."""
        return self.diameters_px

    def select(self, keep: np.ndarray) -> CraterDetections:
        """The detections picked by a boolean or index array."""
        return CraterDetections(self.centers_px[keep], self.diameters_px[keep], self.score[keep])


def circle_iou_matrix(ca: np.ndarray, da: np.ndarray, cb: np.ndarray, db: np.ndarray) -> np.ndarray:
    """Intersection over union (N, M) of discs ``a`` (centres (N, 2), diameters (N,)) and ``b``
    (centres (M, 2), diameters (M,))."""
    ca, cb = np.reshape(ca, (-1, 2)).astype(float), np.reshape(cb, (-1, 2)).astype(float)
    return circle_iou_pairs(ca[:, None, :], np.ravel(da)[:, None], cb[None, :, :], np.ravel(db)[None, :])


def circle_iou_pairs(ca: np.ndarray, da: np.ndarray, cb: np.ndarray, db: np.ndarray) -> np.ndarray:
    """Disc IoU of discs ``a`` and ``b`` element by element (centres (..., 2), diameters (...),
    broadcast against each other)."""
    ra, rb = 0.5 * np.asarray(da, dtype=float), 0.5 * np.asarray(db, dtype=float)
    d = np.linalg.norm(np.asarray(ca, dtype=float) - np.asarray(cb, dtype=float), axis=-1)
    small, big = np.minimum(ra, rb), np.maximum(ra, rb)
    with np.errstate(invalid="ignore", divide="ignore"):
        # lens area of two circles at distance d (where they cut each other)
        a1 = ra**2 * np.arccos(np.clip((d**2 + ra**2 - rb**2) / (2 * d * ra), -1.0, 1.0))
        a2 = rb**2 * np.arccos(np.clip((d**2 + rb**2 - ra**2) / (2 * d * rb), -1.0, 1.0))
        k = (-d + ra + rb) * (d + ra - rb) * (d - ra + rb) * (d + ra + rb)
        lens = a1 + a2 - 0.5 * np.sqrt(np.clip(k, 0.0, None))
    inter = np.where(d >= ra + rb, 0.0, np.where(d <= big - small, np.pi * small**2, lens))
    union = np.pi * (ra**2 + rb**2) - inter
    return inter / np.maximum(union, 1e-12)


def circle_nms(centers_px: np.ndarray, diameters_px: np.ndarray, score: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices kept by greedy NMS on disc IoU, best score first."""
    n = len(score)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    from scipy.spatial import cKDTree

    order = np.argsort(-np.asarray(score), kind="stable")
    c, d = np.asarray(centers_px, float)[order], np.asarray(diameters_px, float)[order]
    tree = cKDTree(c)
    d_max = float(d.max())
    keep: list[int] = []
    suppressed = np.zeros(n, dtype=bool)
    for a in range(n):
        if suppressed[a]:
            continue
        keep.append(a)
        near = np.asarray(tree.query_ball_point(c[a], 0.5 * (d[a] + d_max)), dtype=np.int64)
        near = near[(near > a) & ~suppressed[near]]
        if len(near):
            iou = circle_iou_matrix(c[a:a + 1], d[a:a + 1], c[near], d[near])[0]
            suppressed[near[iou > iou_threshold]] = True
    return order[np.asarray(keep, dtype=np.int64)]

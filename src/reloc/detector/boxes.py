"""Detection boxes: the :class:`Detections` result type, IoU and greedy non-maximum suppression."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Detections:
    """Boxes found in one image: ``boxes_xyxy`` (N, 4) pixel edges (x0, y0, x1, y1) in the input
    image, ``score`` (N,) in [0, 1], ``class_id`` (N,) int (0 for the project's rock models)."""

    boxes_xyxy: np.ndarray
    score: np.ndarray
    class_id: np.ndarray

    @staticmethod
    def empty() -> Detections:
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return int(self.boxes_xyxy.shape[0])

    @property
    def centers_px(self) -> np.ndarray:
        """Box centres (N, 2) (u, v) in pixels."""
        b = self.boxes_xyxy
        return np.column_stack([0.5 * (b[:, 0] + b[:, 2]), 0.5 * (b[:, 1] + b[:, 3])])

    @property
    def sizes_px(self) -> np.ndarray:
        """Box (width, height) (N, 2) in pixels."""
        b = self.boxes_xyxy
        return np.column_stack([b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]])

    def select(self, keep: np.ndarray) -> Detections:
        """The detections picked by a boolean or index array."""
        return Detections(self.boxes_xyxy[keep], self.score[keep], self.class_id[keep])


def iou_matrix(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> np.ndarray:
    """Intersection over union (N, M) of boxes ``a`` (N, 4) and ``b`` (M, 4)."""
    a = np.reshape(a_xyxy, (-1, 4)).astype(float)
    b = np.reshape(b_xyxy, (-1, 4)).astype(float)
    iw = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    ih = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = iw * ih
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-12)


def nms(boxes_xyxy: np.ndarray, score: np.ndarray, iou_threshold: float, class_id: np.ndarray | None = None) -> np.ndarray:
    """Indices kept by greedy NMS, best score first; boxes of different classes never suppress
    each other. ``boxes_xyxy`` (N, 4), ``score`` (N,)."""
    n = len(score)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    b = np.asarray(boxes_xyxy, dtype=float)
    if class_id is not None and len(np.unique(class_id)) > 1:
        b = b + (np.asarray(class_id, dtype=float) * (b.max() + 1.0))[:, None]  # classes apart
    order = np.argsort(-np.asarray(score), kind="stable")
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        rest = order[1:]
        iw = np.clip(np.minimum(b[i, 2], b[rest, 2]) - np.maximum(b[i, 0], b[rest, 0]), 0, None)
        ih = np.clip(np.minimum(b[i, 3], b[rest, 3]) - np.maximum(b[i, 1], b[rest, 1]), 0, None)
        inter = iw * ih
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)

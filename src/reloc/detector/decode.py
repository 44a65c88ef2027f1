"""Decoding of detector outputs into boxes in model-input pixels.

Two layouts are understood:

- ``centernet-v1`` (the project's models): (1, 5, h, w) per output cell = (centre heat in [0, 1],
  offset x, offset y, log width, log height), offsets and sizes in output cells of ``stride``
  pixels. Peaks are local maxima of the heat over a 3 x 3 window above the score threshold.
- ``crater-centernet-v1`` (the crater model): (1, 4, h, w), the same with one log diameter.
- Ultralytics YOLOv8/11/12 ONNX export: (1, 4 + nc, N) = per anchor (cx, cy, w, h) in input pixels
  followed by nc class scores (already sigmoid); (1, N, 4 + nc) is accepted too. Boxes are
  thresholded on their best class score and suppressed per class by NMS.
"""

from __future__ import annotations

import cv2
import numpy as np

from reloc.detector.boxes import nms


def heat_peaks(heat: np.ndarray, score_threshold: float, max_detections: int):
    """Rows (N,), columns (N,) and scores (N,) of the local maxima of ``heat`` (h, w) over a 3 x 3
    window at or above ``score_threshold``, at most ``max_detections`` (the best)."""
    heat = np.ascontiguousarray(heat, dtype=np.float32)
    peak = heat >= cv2.dilate(heat, np.ones((3, 3), np.uint8))
    ii, jj = np.nonzero(peak & (heat >= score_threshold))
    score = heat[ii, jj]
    if len(score) > max_detections:
        top = np.argsort(-score, kind="stable")[:max_detections]
        ii, jj, score = ii[top], jj[top], score[top]
    return ii, jj, score


def decode_centernet(out: np.ndarray, stride: int, score_threshold: float, max_detections: int):
    """Boxes (N, 4) xyxy in input pixels and scores (N,) from a (1, 5, h, w) centernet output."""
    ii, jj, score = heat_peaks(out[0, 0], score_threshold, max_detections)
    cx = (jj + out[0, 1, ii, jj]) * stride
    cy = (ii + out[0, 2, ii, jj]) * stride
    w = np.exp(np.clip(out[0, 3, ii, jj], -5.0, 8.0)) * stride
    h = np.exp(np.clip(out[0, 4, ii, jj], -5.0, 8.0)) * stride
    boxes = np.column_stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]).astype(np.float32)
    return boxes.reshape(-1, 4), score.astype(np.float32)


def yolo_channels_first(shape: tuple[int, ...]) -> bool:
    """True when a rank-3 YOLO output (1, A, B) is (1, 4 + nc, N) (anchors along the last axis)."""
    return shape[1] <= shape[2]


def decode_yolo(out: np.ndarray, score_threshold: float, iou_threshold: float, max_detections: int):
    """Boxes (N, 4) xyxy in input pixels, scores (N,) and class ids (N,) from an Ultralytics
    (1, 4 + nc, N) or (1, N, 4 + nc) output, after per-class NMS."""
    pred = out[0] if yolo_channels_first(out.shape) else out[0].T  # (4 + nc, N)
    cls_scores = pred[4:]
    class_id = np.argmax(cls_scores, axis=0)
    score = cls_scores[class_id, np.arange(pred.shape[1])]
    keep = np.flatnonzero(score >= score_threshold)
    cx, cy, w, h = pred[0, keep], pred[1, keep], pred[2, keep], pred[3, keep]
    boxes = np.column_stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]).astype(np.float32).reshape(-1, 4)
    score, class_id = score[keep].astype(np.float32), class_id[keep].astype(np.int64)
    kept = nms(boxes, score, iou_threshold, class_id)[:max_detections]
    return boxes[kept], score[kept], class_id[kept]


def decode_craters(out: np.ndarray, stride: int, score_threshold: float, max_detections: int):
    """Centres (N, 2) and rim diameters (N,) in input pixels and scores (N,) from a (1, 4, h, w)
    ``crater-centernet-v1`` output: per cell (centre heat in [0, 1], offset x, offset y, log
    diameter), offsets and diameter in output cells of ``stride`` pixels; peaks as for boxes."""
    ii, jj, score = heat_peaks(out[0, 0], score_threshold, max_detections)
    cx = (jj + out[0, 1, ii, jj]) * stride
    cy = (ii + out[0, 2, ii, jj]) * stride
    d = np.exp(np.clip(out[0, 3, ii, jj], -5.0, 8.0)) * stride
    return np.column_stack([cx, cy]).astype(np.float32).reshape(-1, 2), d.astype(np.float32), score.astype(np.float32)

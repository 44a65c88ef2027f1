"""Rock detector inference with onnxruntime.

``RockDetector()`` loads the shipped nadir model, ``RockDetector(kind="rover")`` the rover model,
``RockDetector("my_yolo11.onnx", kind="rover")`` a user's Ultralytics export. The model file is
checked on load (one input N x C x H x W with C = 1 or 3, an output layout this module decodes,
and one dry run whose output shape must agree); anything else raises :class:`DetectorError`
naming the file and the problem.

Pre-processing: grey or RGB uint8 images are converted to the model's channel count and scaled to
[0, 1]. Nadir images are cut into overlapping tiles of the model's input size at their native
resolution (a ground sample distance must not change); a tile keeps only the detections whose
centre lies in its own core, so overlaps produce no duplicates. Rover images are letterboxed
(scaled to fit, padded with grey 114 around, as Ultralytics does).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from reloc.detector.boxes import Detections, nms
from reloc.detector.decode import decode_centernet, decode_yolo, yolo_channels_first
from reloc.detector.errors import DetectorError
from reloc.detector.session import image_input, open_session, run_session

log = logging.getLogger(__name__)

KINDS = ("nadir", "rover")
CENTERNET = "centernet-v1"
YOLO = "yolo"
PAD_VALUE = 114
ROCK_TILE_OVERLAP_PX = 64


def default_model_path(kind: str) -> Path:
    """Path of the shipped model of ``kind`` ("nadir" or "rover") inside the package."""
    if kind not in KINDS:
        raise DetectorError(f"detector kind must be one of {KINDS}, got {kind!r}")
    return Path(str(resources.files("reloc.models").joinpath(f"rocks_{kind}.onnx")))


@dataclass(frozen=True)
class DetectorConfig:
    """Inference settings; ``score_threshold`` None takes the model's own (metadata) or 0.25."""

    score_threshold: float | None = None
    iou_threshold: float = 0.5
    max_detections: int = 1000
    tile: bool | None = None  # None: tile nadir images, letterbox rover images
    tile_overlap_px: int | None = None  # None: the detector's own (rocks 64 px, craters 128 px)
    threads: int = 1  # onnxruntime intra-op threads
    input_size_wh: tuple[int, int] | None = None  # for models with dynamic H/W and no metadata


class RockDetector:
    """An ONNX rock detector; :meth:`detect` maps an image to :class:`Detections`."""

    def __init__(self, model_path: str | Path | None = None, kind: str = "nadir", config: DetectorConfig = DetectorConfig()) -> None:
        if kind not in KINDS:
            raise DetectorError(f"detector kind must be one of {KINDS}, got {kind!r}")
        self.kind = kind
        self.config = config
        self.path = Path(model_path) if model_path is not None else default_model_path(kind)
        self.session, meta = open_session(self.path, config.threads)
        self.layout = CENTERNET if meta.get("fgslam_layout") == CENTERNET else YOLO
        self.stride = int(meta.get("stride", 4))
        self._check_io(meta)
        thr = config.score_threshold if config.score_threshold is not None else float(meta.get("score_threshold", 0.25))
        self.score_threshold = thr
        self.tile = config.tile if config.tile is not None else kind == "nadir"
        self._dry_run()
        log.debug("loaded %s detector %s (%s, input %s)", kind, self.path, self.layout, self.input_size_wh)

    def _check_io(self, meta: dict) -> None:
        outs = self.session.get_outputs()
        self.input_name, self.channels, shape = image_input(self.session, self.path)
        fixed = isinstance(shape[2], int) and isinstance(shape[3], int)
        if fixed:
            self.input_size_wh = (int(shape[3]), int(shape[2]))
        elif self.config.input_size_wh is not None:
            self.input_size_wh = tuple(int(v) for v in self.config.input_size_wh)
        elif "input_size" in meta:
            self.input_size_wh = tuple(int(v) for v in meta["input_size"].split(","))
        else:
            self.input_size_wh = (640, 640)
        if self.input_size_wh[0] % 32 and self.layout == YOLO or min(self.input_size_wh) < 32:
            raise DetectorError(f"detector model {self.path}: unusable input size {self.input_size_wh}")
        if len(outs) < 1:
            raise DetectorError(f"detector model {self.path}: no output")
        rank = len(outs[0].shape)
        if meta.get("fgslam_layout") == "crater-centernet-v1":
            raise DetectorError(f"detector model {self.path}: a crater model (layout crater-centernet-v1), not a rock detector")
        if self.layout == CENTERNET and rank != 4 or self.layout == YOLO and rank != 3:
            raise DetectorError(
                f"detector model {self.path}: output {outs[0].name!r} of shape {outs[0].shape} is neither the "
                "project's centernet (1, 5, h, w) nor the Ultralytics YOLO (1, 4 + classes, anchors) layout")

    def _dry_run(self) -> None:
        W, H = self.input_size_wh
        try:
            out = self._run(np.zeros((1, self.channels, H, W), np.float32))
        except DetectorError:
            raise
        except Exception as exc:
            raise DetectorError(f"detector model {self.path}: fails on a {W} x {H} input ({exc})") from exc
        if self.layout == CENTERNET:
            expect = (1, 5, H // self.stride, W // self.stride)
            if tuple(out.shape) != expect:
                raise DetectorError(f"detector model {self.path}: output shape {out.shape}, expected {expect}")
        else:
            a = out.shape[1] if yolo_channels_first(out.shape) else out.shape[2]
            if out.shape[0] != 1 or a < 5:
                raise DetectorError(f"detector model {self.path}: YOLO output shape {out.shape} has no class scores")

    def _run(self, x: np.ndarray) -> np.ndarray:
        return run_session(self.session, self.path, self.input_name, x)

    def _to_model_channels(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if img.ndim == 2:
            return img[:, :, None] if self.channels == 1 else np.repeat(img[:, :, None], 3, axis=2)
        if img.ndim == 3 and img.shape[2] == 3:
            if self.channels == 3:
                return img
            return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)[:, :, None]
        raise DetectorError(f"image must be (H, W) grey or (H, W, 3) RGB, got shape {img.shape}")

    def _infer(self, img_hwc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boxes, scores, classes of one model-input-sized (H, W, C) uint8 array."""
        x = (img_hwc.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
        out = self._run(np.ascontiguousarray(x))
        cfg = self.config
        if self.layout == CENTERNET:
            b, s = decode_centernet(out, self.stride, self.score_threshold, cfg.max_detections)
            return b, s, np.zeros(len(s), np.int64)
        return decode_yolo(out, self.score_threshold, cfg.iou_threshold, cfg.max_detections)

    def detect(self, image: np.ndarray) -> Detections:
        """Rocks in ``image`` (H, W) grey or (H, W, 3) RGB, uint8; boxes in its pixel coordinates."""
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise DetectorError(f"image must be uint8, got {img.dtype}")
        if img.ndim < 2 or img.shape[0] < 1 or img.shape[1] < 1:
            raise DetectorError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
        img = self._to_model_channels(img)
        if self.tile:
            boxes, score, cls = self._detect_tiled(img)
        else:
            boxes, score, cls = self._detect_letterbox(img)
        H, W = img.shape[:2]
        if len(boxes):
            boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, W)
            boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, H)
            ok = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
            boxes, score, cls = boxes[ok], score[ok], cls[ok]
        order = np.argsort(-score, kind="stable")
        return Detections(boxes[order], score[order], cls[order])

    def _detect_letterbox(self, img: np.ndarray):
        W, H = self.input_size_wh
        h, w = img.shape[:2]
        r = min(W / w, H / h)
        nw, nh = max(int(round(w * r)), 1), max(int(round(h * r)), 1)
        resized = img if (nw, nh) == (w, h) else cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if r < 1 else cv2.INTER_LINEAR)
        if resized.ndim == 2:
            resized = resized[:, :, None]
        px, py = (W - nw) // 2, (H - nh) // 2
        canvas = np.full((H, W, img.shape[2]), PAD_VALUE, np.uint8)
        canvas[py:py + nh, px:px + nw] = resized
        boxes, score, cls = self._infer(canvas)
        boxes = (boxes - np.array([px, py, px, py], np.float32)) / r
        return boxes, score, cls

    def _detect_tiled(self, img: np.ndarray):
        W, H = self.input_size_wh
        h, w = img.shape[:2]
        ov_px = ROCK_TILE_OVERLAP_PX if self.config.tile_overlap_px is None else self.config.tile_overlap_px
        ov = int(min(ov_px, min(W, H) // 4))  # never more than a quarter tile
        xs = _tile_starts(w, W, ov)
        ys = _tile_starts(h, H, ov)
        all_b, all_s, all_c = [], [], []
        for y0 in ys:
            for x0 in xs:
                tile = np.full((H, W, img.shape[2]), PAD_VALUE, np.uint8)
                part = img[y0:y0 + H, x0:x0 + W]
                tile[:part.shape[0], :part.shape[1]] = part
                b, s, c = self._infer(tile)
                # keep the detections whose centre falls in this tile's core
                cx, cy = 0.5 * (b[:, 0] + b[:, 2]) + x0, 0.5 * (b[:, 1] + b[:, 3]) + y0
                lo_x = x0 + ov / 2 if x0 > 0 else -np.inf
                hi_x = x0 + W - ov / 2 if x0 + W < w else np.inf
                lo_y = y0 + ov / 2 if y0 > 0 else -np.inf
                hi_y = y0 + H - ov / 2 if y0 + H < h else np.inf
                keep = (cx >= lo_x) & (cx < hi_x) & (cy >= lo_y) & (cy < hi_y)
                all_b.append(b[keep] + np.array([x0, y0, x0, y0], np.float32))
                all_s.append(s[keep])
                all_c.append(c[keep])
        boxes, score, cls = np.vstack(all_b), np.concatenate(all_s), np.concatenate(all_c)
        keep = nms(boxes, score, self.config.iou_threshold, cls)
        return boxes[keep], score[keep], cls[keep]


def _tile_starts(n: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of tiles of ``tile`` px covering ``n`` px with at least ``overlap`` px overlap."""
    if n <= tile:
        return [0]
    step = max(tile - overlap, 1)
    starts = list(range(0, n - tile, step))
    starts.append(n - tile)
    return starts

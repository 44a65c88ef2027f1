"""Orbital crater detector: onnxruntime inference of the shipped crater model (or a retrained one)
over an image pyramid, tiled, for images of any size and bit depth.

``CraterDetector().detect(image)`` -> :class:`CraterDetections` (centres and rim diameters in
image pixels, scores). The model (layout ``crater-centernet-v1``) is trained on craters of a
few to about thirty pixels; craters from ``min_diameter_px`` (4) to ``max_diameter_px`` (256)
are found on an image pyramid (:mod:`reloc.detector.image`): level k is the image halved k
times, and keeps the craters whose diameter in its pixels falls in ``band_px`` (the finest level
everything below the band, the coarsest everything above it up to ``top_max_px``). The bands of
neighbouring levels overlap, and the detections of all levels are merged by disc-IoU NMS.

Each level is normalised once as a whole (so tiling changes nothing but the network's view),
then cut into overlapping tiles of the model's input size; a tile keeps the detections whose
centre lies in its core, as the rock detector's tiles do. ``DetectorConfig(tile=False)`` runs
each level in one piece (the same detections away from tile seams, for more memory).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from reloc.detector.circles import CraterDetections, circle_nms
from reloc.detector.decode import decode_craters
from reloc.detector.errors import DetectorError
from reloc.detector.image import half, normalised_grey
from reloc.detector.runtime import DetectorConfig, _tile_starts
from reloc.detector.session import image_input, open_session, run_session

log = logging.getLogger(__name__)

CRATER_LAYOUT = "crater-centernet-v1"
CRATER_MODEL = "craters_orbital.onnx"
SIZE_MULTIPLE = 32  # the network's input sides must be multiples of its coarsest stride
MIN_LEVEL_PX = 32  # no pyramid level smaller than this a side
CRATER_TILE_OVERLAP_PX = 96  # > the largest crater a level keeps plus the network's reach


def default_crater_model_path() -> Path:
    """Path of the shipped crater model inside the package."""
    return Path(str(resources.files("reloc.models").joinpath(CRATER_MODEL)))


@dataclass(frozen=True)
class CraterConfig:
    """Crater sizes (px of the input image) and the pyramid bands (px of a level)."""

    min_diameter_px: float = 4.0
    max_diameter_px: float = 256.0
    band_px: tuple[float, float] = (6.0, 13.0)  # kept at the intermediate levels
    top_max_px: float = 24.0  # largest diameter the coarsest level keeps
    nms_iou: float = 0.5  # disc IoU above which the weaker of two detections goes
    nodata: float | None = None  # pixel value outside the image footprint (NaN always is)


class CraterDetector:
    """An ONNX crater detector; :meth:`detect` maps an image to :class:`CraterDetections`."""

    def __init__(self, model_path: str | Path | None = None, config: DetectorConfig = DetectorConfig(),
                 crater: CraterConfig = CraterConfig()) -> None:
        if not 0 < crater.min_diameter_px < crater.max_diameter_px:
            raise DetectorError(f"crater diameters need 0 < min < max, got {crater.min_diameter_px}, {crater.max_diameter_px}")
        if not 0 < crater.band_px[0] < crater.band_px[1] <= crater.top_max_px:
            raise DetectorError(f"crater band_px {crater.band_px} must satisfy 0 < low < high <= top_max_px")
        self.config, self.crater = config, crater
        self.path = Path(model_path) if model_path is not None else default_crater_model_path()
        self.session, meta = open_session(self.path, config.threads)
        if meta.get("fgslam_layout") != CRATER_LAYOUT:
            raise DetectorError(f"detector model {self.path}: metadata fgslam_layout is {meta.get('fgslam_layout')!r}, "
                                f"expected {CRATER_LAYOUT!r} (a crater model)")
        try:
            self.stride = int(meta.get("stride", ""))
            self.input_size_wh = tuple(int(v) for v in meta.get("input_size", "640,640").split(","))
            thr = float(meta.get("score_threshold", 0.3)) if config.score_threshold is None else float(config.score_threshold)
        except ValueError as exc:
            raise DetectorError(f"detector model {self.path}: bad metadata stride / input_size / score_threshold ({exc})") from None
        if self.stride not in (1, 2, 4, 8) or len(self.input_size_wh) != 2 or min(self.input_size_wh) < SIZE_MULTIPLE:
            raise DetectorError(f"detector model {self.path}: unusable stride {self.stride} or input size {self.input_size_wh}")
        self.score_threshold = thr
        self.input_name, self.channels, _ = image_input(self.session, self.path)
        if self.channels != 1:
            raise DetectorError(f"detector model {self.path}: a crater model takes 1 (grey) channel, not {self.channels}")
        self.tile = True if config.tile is None else bool(config.tile)
        self._dry_run()
        log.debug("loaded crater detector %s (stride %d, tiles %s)", self.path, self.stride, self.input_size_wh)

    def _dry_run(self) -> None:
        H = W = 2 * SIZE_MULTIPLE
        try:
            out = run_session(self.session, self.path, self.input_name, np.zeros((1, 1, H, W), np.float32))
        except DetectorError as exc:
            raise DetectorError(f"{exc}; a crater model takes (1, 1, H, W) with dynamic H, W") from None
        expect = (1, 4, H // self.stride, W // self.stride)
        if tuple(out.shape) != expect:
            raise DetectorError(f"detector model {self.path}: output shape {tuple(out.shape)} on a {W} x {H} input, "
                                f"expected {expect} (heat, offset x, offset y, log diameter)")

    def levels(self, shape_hw: tuple[int, int]) -> int:
        """Pyramid levels used for an image of ``shape_hw``: enough for ``max_diameter_px`` at the
        coarsest level's ``top_max_px``, and no level under ``MIN_LEVEL_PX`` a side."""
        need = 1 + max(int(np.ceil(np.log2(self.crater.max_diameter_px / self.crater.top_max_px))), 0)
        fit = 1 + max(int(np.floor(np.log2(min(shape_hw) / MIN_LEVEL_PX))), 0)
        return max(min(need, fit), 1)

    def band(self, level: int, n_levels: int) -> tuple[float, float]:
        """Diameters (px of ``level``) that ``level`` of ``n_levels`` keeps."""
        lo = 0.0 if level == 0 else self.crater.band_px[0]
        hi = self.crater.top_max_px if level == n_levels - 1 else self.crater.band_px[1]
        return lo, hi

    def detect(self, image: np.ndarray) -> CraterDetections:
        """Craters in ``image`` (H, W) or (H, W, 3), any integer or float dtype (NaN and
        ``nodata`` pixels are outside the footprint); centres and diameters in its pixels."""
        grey, valid = normalised_grey(image, self.crater.nodata)
        n_levels = self.levels(grey.shape)
        cs, ds, ss = [], [], []
        level = grey
        for k in range(n_levels):
            if k:
                level = half(level)
            c, d, s = self.detect_level(level)
            lo, hi = self.band(k, n_levels)
            keep = (d >= lo) & (d <= hi)
            cs.append(c[keep] * 2**k)
            ds.append(d[keep] * 2**k)
            ss.append(s[keep])
        c, d, s = np.vstack(cs), np.concatenate(ds), np.concatenate(ss)
        H, W = grey.shape
        ok = (d >= self.crater.min_diameter_px) & (d <= self.crater.max_diameter_px)
        ok &= (c[:, 0] >= 0) & (c[:, 0] < W) & (c[:, 1] >= 0) & (c[:, 1] < H)
        c, d, s = c[ok], d[ok], s[ok]
        if len(s) and not valid.all():
            on = valid[c[:, 1].astype(int), c[:, 0].astype(int)]
            c, d, s = c[on], d[on], s[on]
        keep = circle_nms(c, d, s, self.crater.nms_iou)  # max_detections caps each network pass
        return CraterDetections(c[keep].astype(np.float32), d[keep].astype(np.float32), s[keep].astype(np.float32))

    def detect_level(self, level: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centres (N, 2), diameters (N,), scores (N,)) in the pixels of one normalised pyramid
        level (H, W) float32, every size the network reports, tiled unless ``tile`` is off."""
        h, w = level.shape
        T_w, T_h = self.input_size_wh
        if not self.tile or (h <= T_h and w <= T_w):
            return self._infer(level, 0, 0)
        ov = CRATER_TILE_OVERLAP_PX if self.config.tile_overlap_px is None else int(self.config.tile_overlap_px)
        if ov < 0:
            raise DetectorError(f"tile overlap must be >= 0 px, got {ov}")
        ov = min(ov, min(T_w, T_h) // 4)  # never more than a quarter tile
        cs, ds, ss = [], [], []
        for y0 in _tile_starts(h, T_h, ov):
            for x0 in _tile_starts(w, T_w, ov):
                c, d, s = self._infer(level[y0:y0 + T_h, x0:x0 + T_w], x0, y0)
                lo_x = x0 + ov / 2 if x0 > 0 else -np.inf
                hi_x = x0 + T_w - ov / 2 if x0 + T_w < w else np.inf
                lo_y = y0 + ov / 2 if y0 > 0 else -np.inf
                hi_y = y0 + T_h - ov / 2 if y0 + T_h < h else np.inf
                core = (c[:, 0] >= lo_x) & (c[:, 0] < hi_x) & (c[:, 1] >= lo_y) & (c[:, 1] < hi_y)
                cs.append(c[core])
                ds.append(d[core])
                ss.append(s[core])
        return np.vstack(cs), np.concatenate(ds), np.concatenate(ss)

    def _infer(self, part: np.ndarray, x0: int, y0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detections of one piece (h, w) of a level at (x0, y0), in level pixels; the piece is
        padded (edge values) up to multiples of SIZE_MULTIPLE, and centres in the padding dropped."""
        h, w = part.shape
        ph, pw = -h % SIZE_MULTIPLE, -w % SIZE_MULTIPLE
        x = cv2.copyMakeBorder(part, 0, ph, 0, pw, cv2.BORDER_REPLICATE) if ph or pw else part
        out = run_session(self.session, self.path, self.input_name, np.ascontiguousarray(x[None, None], np.float32))
        c, d, s = decode_craters(out, self.stride, self.score_threshold, self.config.max_detections)
        inside = (c[:, 0] < w) & (c[:, 1] < h)
        return c[inside] + np.array([x0, y0], np.float32), d[inside], s[inside]

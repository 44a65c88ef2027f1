"""Stereo rock positions: rover detections on a rectified pair -> 3D rock centres with covariance
in the left camera's optical frame (z forward, x right, y down; metres).

Two ways to a disparity per left-image box:

- ``sgbm``: OpenCV semi-global matching over the pair, then the median of the valid disparities
  in the box core (the central ``box_core_fraction`` of the box, which lies on the rock);
- ``match``: the left and right detections are paired (same rows within ``match_max_dv_px``,
  similar size, positive disparity; optimal assignment), and each pair's disparity is refined by
  normalised cross-correlation of the left box patch along the right image row (sub-pixel
  parabola fit).

A pixel (u, v) with disparity d gives X = (u - cx) b / d, Y = (v - cy) b / d, Z = f b / d: the
rock's visible front surface. The rock centre lies about ``center_offset_fraction`` of a diameter
further along the line of sight. The covariance is the first-order propagation of the pixel and
disparity errors (``sigma_pixel_px``, ``sigma_disparity_px``; depth sigma = Z^2 sigma_d / (f b)),
plus the uncertainty of that centre offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from reloc.detector.boxes import Detections
from reloc.errors import RelocError


class StereoError(RelocError, ValueError):
    """Bad stereo input (image sizes, rig parameters)."""


@dataclass(frozen=True)
class StereoRig:
    """Rectified stereo rig: focal length and principal point (pixels) and baseline (metres)."""

    f_px: float
    cx_px: float
    cy_px: float
    baseline_m: float

    def __post_init__(self) -> None:
        if not (self.f_px > 0 and self.baseline_m > 0):
            raise StereoError(f"stereo rig needs f_px > 0 and baseline_m > 0, got {self.f_px}, {self.baseline_m}")


@dataclass(frozen=True)
class TriangulationConfig:
    """Disparity method and the stereo error model (defaults for rendered 640 px images)."""

    method: str = "sgbm"  # "sgbm" or "match"
    sigma_disparity_px: float = 0.25
    sigma_pixel_px: float = 1.0
    min_disparity_px: float = 1.0
    num_disparities: int = 96  # SGBM search range (multiple of 16): closest depth f b / 96
    block_size: int = 5
    box_core_fraction: float = 0.5
    min_valid_fraction: float = 0.2  # of the box core pixels with a valid SGBM disparity
    center_offset_fraction: float = 0.3  # rock centre behind its visible surface, in diameters
    center_offset_sigma_fraction: float = 0.12  # along the line of sight, in diameters
    center_lateral_sigma_fraction: float = 0.07  # box centre vs rock centre (partial views), in diameters
    match_max_dv_px: float = 4.0
    match_max_size_ratio: float = 1.6
    match_search_px: int = 4


@dataclass(frozen=True)
class RockPoints:
    """Triangulated rocks: ``xyz_cam_m`` (N, 3) centres in the left optical frame, ``cov_cam_m2``
    (N, 3, 3), ``size_m`` (N,) diameters, ``score`` (N,), ``index`` (N,) the left detection each
    came from, ``disparity_px`` (N,)."""

    xyz_cam_m: np.ndarray
    cov_cam_m2: np.ndarray
    size_m: np.ndarray
    score: np.ndarray
    index: np.ndarray
    disparity_px: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz_cam_m.shape[0])


def triangulate(uv_px: np.ndarray, disparity_px: np.ndarray, rig: StereoRig, sigma_pixel_px: float,
                sigma_disparity_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) in the left optical frame and their covariance (N, 3, 3) from pixels
    ``uv_px`` (N, 2) and disparities (N,) > 0, by first-order error propagation."""
    uv = np.reshape(uv_px, (-1, 2)).astype(float)
    d = np.reshape(disparity_px, (-1,)).astype(float)
    if np.any(d <= 0):
        raise StereoError("disparities must be > 0")
    b, f = rig.baseline_m, rig.f_px
    du, dv = uv[:, 0] - rig.cx_px, uv[:, 1] - rig.cy_px
    xyz = np.column_stack([du * b / d, dv * b / d, f * b / d])
    J = np.zeros((len(d), 3, 3))
    J[:, 0, 0] = b / d
    J[:, 1, 1] = b / d
    J[:, 0, 2] = -du * b / d**2
    J[:, 1, 2] = -dv * b / d**2
    J[:, 2, 2] = -f * b / d**2
    S = np.diag([sigma_pixel_px**2, sigma_pixel_px**2, sigma_disparity_px**2])
    cov = J @ S @ np.swapaxes(J, 1, 2)
    return xyz, cov


def _to_centres(xyz_surface: np.ndarray, cov: np.ndarray, size_m: np.ndarray, cfg: TriangulationConfig):
    """Move surface points back along the line of sight to the rock centre; widen the covariance."""
    ray = xyz_surface / np.linalg.norm(xyz_surface, axis=1, keepdims=True)
    xyz = xyz_surface + cfg.center_offset_fraction * size_m[:, None] * ray
    s2 = (cfg.center_offset_sigma_fraction * size_m) ** 2
    s2_iso = (cfg.center_lateral_sigma_fraction * size_m) ** 2
    cov = cov + s2[:, None, None] * np.einsum("ni,nj->nij", ray, ray) + (s2_iso[:, None, None] + 1e-6) * np.eye(3)
    return xyz, 0.5 * (cov + np.swapaxes(cov, 1, 2))


def sgbm_disparity(left: np.ndarray, right: np.ndarray, cfg: TriangulationConfig = TriangulationConfig()) -> np.ndarray:
    """Left-image disparity (H, W) float32 in pixels from grey uint8 images (NaN where invalid)."""
    nd = int(np.ceil(cfg.num_disparities / 16) * 16)
    bs = cfg.block_size
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs,
                                 uniquenessRatio=5, speckleWindowSize=50, speckleRange=2, disp12MaxDiff=1,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(left, right).astype(np.float32) / 16.0
    disp[disp < cfg.min_disparity_px] = np.nan
    return disp


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    if left.shape != right.shape or left.ndim != 2 or left.dtype != np.uint8 or right.dtype != np.uint8:
        raise StereoError(f"stereo images must be grey uint8 of one size, got {left.shape} {left.dtype} and {right.shape} {right.dtype}")


def _points(dets: Detections, idx: np.ndarray, disp: np.ndarray, rig: StereoRig, cfg: TriangulationConfig) -> RockPoints:
    uv = dets.centers_px[idx]
    xyz, cov = triangulate(uv, disp, rig, cfg.sigma_pixel_px, cfg.sigma_disparity_px)
    size = dets.sizes_px[idx, 0] * xyz[:, 2] / rig.f_px
    xyz, cov = _to_centres(xyz, cov, size, cfg)
    return RockPoints(xyz, cov, size, dets.score[idx], idx.astype(np.int64), disp.astype(float))


def triangulate_sgbm(left: np.ndarray, right: np.ndarray, dets_left: Detections, rig: StereoRig,
                     cfg: TriangulationConfig = TriangulationConfig(), disparity: np.ndarray | None = None) -> RockPoints:
    """Rock centres of the left detections from the SGBM disparity inside each box core."""
    _check_pair(left, right)
    disp = sgbm_disparity(left, right, cfg) if disparity is None else disparity
    H, W = left.shape
    idx, dvals = [], []
    for k, (x0, y0, x1, y1) in enumerate(dets_left.boxes_xyxy):
        m = 0.5 * (1 - cfg.box_core_fraction)
        a0, a1 = int(np.floor(x0 + m * (x1 - x0))), int(np.ceil(x1 - m * (x1 - x0)))
        b0, b1 = int(np.floor(y0 + m * (y1 - y0))), int(np.ceil(y1 - m * (y1 - y0)))
        core = disp[max(b0, 0):min(max(b1, b0 + 1), H), max(a0, 0):min(max(a1, a0 + 1), W)]
        valid = core[np.isfinite(core)]
        if core.size == 0 or valid.size < max(cfg.min_valid_fraction * core.size, 1):
            continue
        idx.append(k)
        dvals.append(float(np.median(valid)))
    return _points(dets_left, np.asarray(idx, dtype=np.int64), np.asarray(dvals), rig, cfg)


def match_detections(dets_left: Detections, dets_right: Detections, cfg: TriangulationConfig = TriangulationConfig()):
    """Pairs (left index (M,), right index (M,)) of detections of one rock in a rectified pair."""
    if len(dets_left) == 0 or len(dets_right) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cl, cr = dets_left.centers_px, dets_right.centers_px
    sl, sr = dets_left.sizes_px, dets_right.sizes_px
    dv = np.abs(cl[:, None, 1] - cr[None, :, 1])
    d = cl[:, None, 0] - cr[None, :, 0]
    ratio = np.exp(np.abs(np.log(np.maximum(sl[:, None, :], 1e-3) / np.maximum(sr[None, :, :], 1e-3)))).max(axis=2)
    ok = (dv <= cfg.match_max_dv_px) & (d >= cfg.min_disparity_px) & (ratio <= cfg.match_max_size_ratio)
    cost = np.where(ok, dv / cfg.match_max_dv_px + (ratio - 1.0) + 1e-3 * d, 1e6)
    li, ri = linear_sum_assignment(cost)
    keep = ok[li, ri]
    return li[keep].astype(np.int64), ri[keep].astype(np.int64)


def _refine(left: np.ndarray, right: np.ndarray, box, d0: float, search: int) -> float | None:
    """Disparity of the left ``box`` near ``d0`` by NCC along the right row, to a sub-pixel."""
    H, W = left.shape
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    tpl = left[y0:y1, x0:x1]
    r0 = int(round(x0 - d0)) - search
    r1 = int(round(x1 - d0)) + search
    if r0 < 0 or r1 > W:
        return None
    res = cv2.matchTemplate(right[y0:y1, r0:r1], tpl, cv2.TM_CCOEFF_NORMED)[0]
    k = int(np.argmax(res))
    if res[k] < 0.5:
        return None
    off = 0.0
    if 0 < k < len(res) - 1:
        den = res[k - 1] - 2 * res[k] + res[k + 1]
        off = 0.5 * (res[k - 1] - res[k + 1]) / den if den < 0 else 0.0
    return float(x0 - (r0 + k + off))


def triangulate_matched(left: np.ndarray, right: np.ndarray, dets_left: Detections, dets_right: Detections,
                        rig: StereoRig, cfg: TriangulationConfig = TriangulationConfig()) -> RockPoints:
    """Rock centres from matched left/right detections, disparities refined by NCC."""
    _check_pair(left, right)
    li, ri = match_detections(dets_left, dets_right, cfg)
    idx, dvals = [], []
    for a, b in zip(li, ri):
        d0 = float(dets_left.centers_px[a, 0] - dets_right.centers_px[b, 0])
        d = _refine(left, right, dets_left.boxes_xyxy[a], d0, cfg.match_search_px)
        d = d0 if d is None else d
        if d >= cfg.min_disparity_px:
            idx.append(a)
            dvals.append(d)
    return _points(dets_left, np.asarray(idx, dtype=np.int64), np.asarray(dvals), rig, cfg)


def rock_points(left: np.ndarray, right: np.ndarray, dets_left: Detections, rig: StereoRig,
                cfg: TriangulationConfig = TriangulationConfig(), dets_right: Detections | None = None) -> RockPoints:
    """Rock centres by ``cfg.method`` ("sgbm", or "match", which needs ``dets_right``)."""
    if cfg.method == "sgbm":
        return triangulate_sgbm(left, right, dets_left, rig, cfg)
    if cfg.method == "match":
        if dets_right is None:
            raise StereoError("method 'match' needs the right-image detections")
        return triangulate_matched(left, right, dets_left, dets_right, rig, cfg)
    raise StereoError(f"stereo method must be 'sgbm' or 'match', got {cfg.method!r}")

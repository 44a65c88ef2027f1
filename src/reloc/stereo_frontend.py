"""The rover's image front-end: one rectified stereo pair -> rock observations in base_link.

Detect rocks in the left image (the ONNX rover detector, :class:`reloc.detector.RockDetector`; in
the right one too for the ``match`` disparity), triangulate them (:func:`reloc.stereo.rock_points`),
keep those within the stereo range gate and move centres and covariances from the left optical
frame into base_link with ``T_base_cam``. The simulator's image path (``sim.image_detections``)
and the bag front-end (``fgslam.io.image_rocks``) both call :meth:`StereoFrontEnd.frame`, so a
rendered frame and the same frame read back from a bag give the same observation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from reloc.config import NonNegative, Positive, checked
from reloc.errors import ConfigError
from reloc.measurements import RockObservations

if TYPE_CHECKING:  # reloc.stereo imports OpenCV: only when a front-end is made
    from reloc.stereo import RockPoints, StereoRig, TriangulationConfig


@dataclass(frozen=True)
@checked(ConfigError)
class FrontEndConfig:
    """Range gate (m, from the left camera), disparity method, minimum reported diameter (m), and
    the detector's score threshold (None: the model's own)."""

    min_range_m: NonNegative = 0.6
    max_range_m: Positive = 10.0
    method: Literal["sgbm", "match"] = "sgbm"
    min_size_m: Positive = 1e-3
    score_threshold: float | None = None
    threads: int = 1  # onnxruntime intra-op threads of the detector


@dataclass(frozen=True)
class FrontEndFrame:
    """One pair's result: ``observations`` in base_link, ``boxes_left`` (N, 4) the left boxes they
    came from, and the time spent detecting and triangulating (s)."""

    observations: RockObservations
    boxes_left: np.ndarray
    detect_s: float
    stereo_s: float


@dataclass
class StereoFrontEnd:
    """Detector + rig + mounting (see module doc). ``detector`` defaults to the shipped rover model."""

    rig: StereoRig
    T_base_cam: np.ndarray
    config: FrontEndConfig = field(default_factory=FrontEndConfig)
    triangulation: TriangulationConfig | None = None
    detector: object | None = None

    def __post_init__(self) -> None:
        T = np.asarray(self.T_base_cam, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ConfigError(f"T_base_cam must be a finite (4, 4) transform, got shape {T.shape}")
        self.T_base_cam = T
        if self.triangulation is None:
            from reloc.stereo import TriangulationConfig

            self.triangulation = TriangulationConfig(method=self.config.method)
        if self.detector is None:
            from reloc.detector import DetectorConfig, RockDetector

            self.detector = RockDetector(kind="rover", config=DetectorConfig(
                score_threshold=self.config.score_threshold, threads=self.config.threads))

    def frame(self, t_s: float, left: np.ndarray, right: np.ndarray) -> FrontEndFrame:
        """Rocks of the rectified pair (``left``, ``right``: (H, W) uint8) stamped ``t_s``."""
        from reloc.stereo import rock_points

        t0 = time.perf_counter()
        dl = self.detector.detect(left)
        dr = self.detector.detect(right) if self.triangulation.method == "match" else None
        t1 = time.perf_counter()
        rp = rock_points(left, right, dl, self.rig, self.triangulation, dr)
        obs, keep = self.to_base(t_s, rp)
        t2 = time.perf_counter()
        return FrontEndFrame(obs, dl.boxes_xyxy[rp.index[keep]], t1 - t0, t2 - t1)

    def to_base(self, t_s: float, rp: RockPoints) -> tuple[RockObservations, np.ndarray]:
        """Range-gated rock points -> RockObservations in base_link, and the kept mask."""
        cfg = self.config
        R_bc, t_bc = self.T_base_cam[:3, :3], self.T_base_cam[:3, 3]
        rng_m = np.linalg.norm(rp.xyz_cam_m, axis=1)
        keep = (rng_m >= cfg.min_range_m) & (rng_m <= cfg.max_range_m)
        xyz_b = rp.xyz_cam_m[keep] @ R_bc.T + t_bc
        cov_b = np.einsum("ij,njk,lk->nil", R_bc, rp.cov_cam_m2[keep], R_bc)
        obs = RockObservations(float(t_s), xyz_b, 0.5 * (cov_b + np.swapaxes(cov_b, 1, 2)),
                               np.maximum(rp.size_m[keep], cfg.min_size_m), rp.score[keep])
        return obs, keep

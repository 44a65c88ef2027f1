"""Rock measurements through pixels: render the rover's stereo pair and the orbital image, run the
ONNX detectors and triangulate, instead of the statistical detector models of ``sim.sensors``.

``image_rock_observations`` gives, per stereo frame, a :class:`RockObservations` in base_link
(same contract as the statistical path) and the true rock row behind each detection (read from
the renderer's instance image at the box core, -1 for a false positive), so the run's detection
precision and recall are measured, not assumed. ``image_catalog`` renders the nadir image of the
whole world and turns the nadir detector's boxes into a world-frame :class:`RockCatalog`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from reloc.measurements import RockCatalog, RockObservations
from sim.config import StereoConfig
from sim.datasets import box_labels, rover_camera
from sim.render import Appearance, Lighting, Renderer
from sim.sensors.stereo import StereoCamera
from sim.world import World

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageDetectionConfig:
    """Rendering and detection settings of the image path."""

    width_px: int = 640  # rendered mast camera columns (field of view from StereoConfig)
    rate_hz: float | None = None  # None: StereoConfig.rate_hz
    method: str = "sgbm"  # stereo disparity: "sgbm" or "match"
    orbital_gsd_m: float = 0.05
    lighting: Lighting = field(default_factory=Lighting)
    appearance: Appearance = field(default_factory=Appearance)
    min_label_area_px: float = 30.0  # visible rocks smaller than this are not counted as missed


@dataclass
class ImageObservations:
    """Per frame: ``observations`` (RockObservations), ``rock`` (true rock row per detection, -1:
    false), ``visible`` (rock rows of labelled visible rocks); ``stats`` precision/recall/timings."""

    observations: list[RockObservations]
    rock: list[np.ndarray]
    visible: list[np.ndarray]
    stats: dict


def _box_rock(instance: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """The rock row (-1: none) most frequent in the central half of each box (N, 4)."""
    H, W = instance.shape
    out = np.full(len(boxes), -1, dtype=np.int64)
    for k, (x0, y0, x1, y1) in enumerate(boxes):
        a0, a1 = int(x0 + 0.25 * (x1 - x0)), int(np.ceil(x1 - 0.25 * (x1 - x0)))
        b0, b1 = int(y0 + 0.25 * (y1 - y0)), int(np.ceil(y1 - 0.25 * (y1 - y0)))
        core = instance[max(b0, 0):min(max(b1, b0 + 1), H), max(a0, 0):min(max(a1, a0 + 1), W)].ravel()
        on_rock = core[core >= 0]
        if on_rock.size:
            vals, counts = np.unique(on_rock, return_counts=True)
            if counts.max() >= 0.3 * core.size:
                out[k] = vals[np.argmax(counts)]
    return out


def stereo_front_end(stereo_cfg: StereoConfig, cfg: ImageDetectionConfig, detector=None):
    """The rover front-end (:class:`reloc.stereo_frontend.StereoFrontEnd`) of the rendered mast
    camera: its rig, its mounting and the stereo range gate of ``stereo_cfg``."""
    from reloc.stereo import StereoRig
    from reloc.stereo_frontend import FrontEndConfig, StereoFrontEnd

    cam = rover_camera(stereo_cfg, cfg.width_px)
    rig = StereoRig(cam.f_px, cam.cx_px, cam.cy_px, stereo_cfg.baseline_m)
    fe_cfg = FrontEndConfig(min_range_m=stereo_cfg.min_range_m, max_range_m=stereo_cfg.max_range_m, method=cfg.method)
    return StereoFrontEnd(rig, StereoCamera.from_config(stereo_cfg).T_base_cam, fe_cfg, detector=detector), cam


def image_rock_observations(
    world: World, t_s: np.ndarray, T_world_base: np.ndarray, stereo_cfg: StereoConfig = StereoConfig(),
    detector=None, cfg: ImageDetectionConfig = ImageDetectionConfig(), progress: Callable[[], None] | None = None,
    on_frame: Callable[[float, object], None] | None = None,
) -> ImageObservations:
    """Detections of the rendered stereo pairs at base poses ``T_world_base`` (F, 4, 4), times
    ``t_s`` (F,) seconds; ``detector`` defaults to the shipped rover model. ``on_frame(t, render)``
    receives every rendered pair (:class:`sim.render.stereo.StereoRender`), e.g. to record it."""
    import time

    front, cam = stereo_front_end(stereo_cfg, cfg, detector)
    renderer = Renderer(world, cfg.appearance)
    obs, rocks, visible = [], [], []
    n_true = n_det = n_vis = 0
    t_render = t_detect = t_stereo = 0.0
    for t, T_wb in zip(np.asarray(t_s, dtype=float), np.asarray(T_world_base, dtype=float)):
        t0 = time.perf_counter()
        sr = renderer.stereo(T_wb @ front.T_base_cam, cam, stereo_cfg.baseline_m, cfg.lighting)
        t_render += time.perf_counter() - t0
        if on_frame is not None:
            on_frame(float(t), sr)
        fr = front.frame(float(t), sr.left, sr.right)
        t_detect, t_stereo = t_detect + fr.detect_s, t_stereo + fr.stereo_s
        obs.append(fr.observations)
        truth = _box_rock(sr.instance_left, fr.boxes_left)
        lab = box_labels(sr.instance_left, cfg.min_label_area_px, 5.0)
        in_range = np.linalg.norm(world.rocks.xyz_m[lab.rock] - sr.T_world_left[:3, 3], axis=1) <= stereo_cfg.max_range_m
        vis = lab.rock[~lab.ignore & in_range]
        rocks.append(truth)
        visible.append(vis)
        n_det += len(truth)
        n_true += len(np.intersect1d(truth[truth >= 0], vis))
        n_vis += len(vis)
        if progress is not None:
            progress()
    F = max(len(obs), 1)
    stats = {
        "n_frames": len(obs), "n_detections": n_det, "n_visible": n_vis,
        "precision": n_true / max(n_det, 1), "recall": n_true / max(n_vis, 1),
        "render_s_per_frame": t_render / F, "detect_s_per_frame": t_detect / F, "stereo_s_per_frame": t_stereo / F,
    }
    log.info("image detections: %d frames, precision %.3f recall %.3f", len(obs), stats["precision"], stats["recall"])
    return ImageObservations(obs, rocks, visible, stats)


def image_catalog(world: World, gsd_m: float = 0.05, detector=None, lighting: Lighting = Lighting(),
                  appearance: Appearance = Appearance()) -> tuple[RockCatalog, np.ndarray]:
    """The nadir-detector catalog of ``world`` rendered at ``gsd_m``: (catalog in world metres,
    true rock row per entry (-1: false positive)); ``detector`` defaults to the shipped nadir model."""
    from reloc.detector import RockDetector
    from reloc.detector.catalog import catalog_from_detections

    det = detector if detector is not None else RockDetector(kind="nadir")
    nr = Renderer(world, appearance).nadir(gsd_m, lighting)
    d = det.detect(nr.image)
    catalog = catalog_from_detections(d, gsd_m, (nr.extent[0], nr.extent[3]))
    return catalog, _box_rock(nr.instance, d.boxes_xyxy)


def with_image_detections(run, cfg: ImageDetectionConfig = ImageDetectionConfig(), rover_detector=None,
                          nadir_detector=None, progress: Callable[[], None] | None = None,
                          on_frame: Callable[[float, object], None] | None = None):
    """A copy of the simulator run ``run`` (:class:`sim.simulate.SimRun`) whose /rocks frames and
    catalog come from rendering and the detectors; every other stream is left untouched. With
    ``cfg.rate_hz`` below the run's stereo rate, frames are thinned to that rate."""
    import dataclasses

    from reloc.measurements import sort_key

    frames = [m for m in run.measurements if isinstance(m, RockObservations)]
    t_frames = np.array([m.t for m in frames])
    stereo_cfg = run.config.sensors.stereo
    if cfg.rate_hz is not None and len(t_frames):
        keep = np.unique(np.searchsorted(t_frames, np.arange(t_frames[0], t_frames[-1] + 1e-9, 1.0 / cfg.rate_hz)))
        t_frames = t_frames[keep[keep < len(t_frames)]]
    gt = run.ground_truth
    idx = np.clip(np.searchsorted(gt.t, t_frames - 1e-9), 0, len(gt.t) - 1)
    img = image_rock_observations(run.world, t_frames, gt.T_world_base[idx], stereo_cfg, rover_detector, cfg, progress,
                                  on_frame)
    catalog, catalog_rock = image_catalog(run.world, cfg.orbital_gsd_m, nadir_detector, cfg.lighting, cfg.appearance)
    meas = [m for m in run.measurements if not isinstance(m, RockObservations)] + img.observations
    meas.sort(key=sort_key)
    n_true = int(np.sum(catalog_rock >= 0))
    stats = dict(run.stats)
    stats.update({
        "detections": "image", "n_stereo_frames": img.stats["n_frames"], "n_visible": img.stats["n_visible"],
        "n_detections": img.stats["n_detections"], "stereo_precision": img.stats["precision"],
        "stereo_recall": img.stats["recall"], "n_catalog": len(catalog),
        "catalog_precision": n_true / max(len(catalog), 1), "catalog_recall": n_true / max(len(run.world.rocks), 1),
        "image_render_s_per_frame": img.stats["render_s_per_frame"],
        "image_detect_s_per_frame": img.stats["detect_s_per_frame"],
        "image_stereo_s_per_frame": img.stats["stereo_s_per_frame"],
    })
    return dataclasses.replace(run, measurements=meas, catalog=catalog, catalog_rock=catalog_rock, stats=stats,
                               stereo_rock=img.rock, stereo_visible=img.visible)

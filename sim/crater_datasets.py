"""Rendered crater data sets for the orbital crater detector: cratered scenes
(:mod:`sim.crater_scene`) through an orbital camera model, with circle labels.

Labels: every crater whose centre lies in the image and whose rim is at least ``min_label_px``
across is a true crater, unless its bowl is hidden in the terrain's own relief
(:func:`sim.crater_scene.visible_craters`). Craters from ``min_listed_px`` up to that size,
hidden ones, and craters centred just outside the image whose rim reaches into it are *ignore*
craters: a detection on them is neither a true nor a false positive (COCO's "crowd" regions).
``train``, ``val`` (choice of the score threshold) and ``eval`` (the benchmark) draw from
disjoint seed streams, so evaluation worlds are never seen in training.

A crater's photometric signal-to-clutter ratio (:func:`signal_to_clutter`, ``CraterSample.scr``
on request): the rms of what the crater adds to the camera image, against the rms of the image
of the same ground without craters, both band-passed at the crater's scale. The labels above
are topographic (a bowl deeper than the relief); albedo texture, haze and noise can still hide
a crater that the relief does not, and the ratio measures that.

The camera (:func:`orbital_sensor`): atmospheric haze, optical blur, exposure, shot and read
noise, column striping and CCD-channel gain seams (HiRISE-like), quantisation to 8 bit or to
10-16 bit in a 16-bit container, and JPEG compression of some 8-bit products.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from sim.crater_scene import CraterScene, SceneVariation, render_crater_scene

SPLITS = {"train": 0, "eval": 1, "val": 2}


@dataclass(frozen=True)
class CraterLabels:
    """Craters of one image: ``centres_px`` (K, 2) (column, row; pixel edges at integers),
    ``diameters_px`` (K,) rim diameters, ``ignore`` (K,) True where a detection counts neither way."""

    centres_px: np.ndarray
    diameters_px: np.ndarray
    ignore: np.ndarray

    def __len__(self) -> int:
        return len(self.diameters_px)

    @property
    def positives(self) -> tuple[np.ndarray, np.ndarray]:
        """(centres (P, 2), diameters (P,)) of the craters that count as ground truth."""
        return self.centres_px[~self.ignore], self.diameters_px[~self.ignore]

    def scaled(self, factor: float, offset_px: tuple[float, float] = (0.0, 0.0)) -> CraterLabels:
        """Labels of the image cropped at ``offset_px`` (column, row) and then resized by ``factor``."""
        c = (self.centres_px - np.asarray(offset_px, float)) * factor
        return CraterLabels(c, self.diameters_px * factor, self.ignore.copy())


def crater_labels(centres_px: np.ndarray, diameters_px: np.ndarray, visible: np.ndarray, shape_hw: tuple[int, int],
                  min_label_px: float = 4.0, min_listed_px: float = 2.0) -> CraterLabels:
    """Labels of an image of ``shape_hw`` from all craters of its scene (module doc)."""
    h, w = shape_hw
    c = np.reshape(centres_px, (-1, 2))
    d = np.ravel(diameters_px)
    r = 0.5 * d
    inside = (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h)
    reaches = (c[:, 0] + r > 0) & (c[:, 0] - r < w) & (c[:, 1] + r > 0) & (c[:, 1] - r < h)
    keep = reaches & (d >= min_listed_px)
    positive = inside & (d >= min_label_px) & np.ravel(visible)
    return CraterLabels(c[keep], d[keep], ~positive[keep])


@dataclass(frozen=True)
class SensorVariation:
    """Ranges of the orbital camera (uniform unless stated; ``*_p`` are probabilities)."""

    haze_p: float = 0.4
    haze: tuple[float, float] = (0.05, 0.6)  # share of the signal replaced by a flat veil
    blur_sigma_px: tuple[float, float] = (0.2, 1.4)
    mean_level: tuple[float, float] = (0.12, 0.65)  # mean signal as a share of full scale
    read_noise: tuple[float, float] = (0.001, 0.02)  # log-uniform, share of full scale
    shot_noise: tuple[float, float] = (0.0, 0.015)  # sigma at full scale, grows as sqrt(signal)
    stripes_p: float = 0.25
    seams_p: float = 0.2
    high_bit_p: float = 0.25  # 10-16 bit data in a uint16 container instead of 8 bit
    jpeg_p: float = 0.3  # of the 8-bit images
    jpeg_quality: tuple[int, int] = (25, 92)


def orbital_sensor(grey: np.ndarray, rng: np.random.Generator, var: SensorVariation = SensorVariation()) -> np.ndarray:
    """The image (H, W) uint8 or uint16 an orbital camera makes of scene radiance ``grey`` (H, W)
    float in [0, 1] (module doc)."""
    img = np.asarray(grey, dtype=np.float32)
    if rng.random() < var.haze_p:
        h = rng.uniform(*var.haze)
        img = (1.0 - h) * img + h * float(img.mean())
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(*var.blur_sigma_px))
    img = img * np.float32(rng.uniform(*var.mean_level) / max(float(img.mean()), 1e-3))
    W = img.shape[1]
    if rng.random() < var.stripes_p:
        img = img * (1.0 + rng.uniform(0.001, 0.01) * rng.standard_normal(W, dtype=np.float32))[None, :]
    if rng.random() < var.seams_p:
        edges = np.sort(rng.integers(0, W, int(rng.integers(1, 4))))
        gain = np.ones(W, np.float32)
        for e in edges:
            gain[e:] *= np.float32(1.0 + rng.uniform(-0.04, 0.04))
        img = img * gain[None, :]
    shot = rng.uniform(*var.shot_noise) * np.sqrt(np.clip(img, 0.0, None))
    lo, hi = np.log(var.read_noise)
    noise_sigma = np.sqrt(shot**2 + np.float32(np.exp(rng.uniform(lo, hi))) ** 2)
    img = img + noise_sigma * rng.standard_normal(img.shape, dtype=np.float32)
    img = np.clip(img, 0.0, 1.0)
    if rng.random() < var.high_bit_p:
        bits = int(rng.choice([10, 12, 14, 16]))
        return np.rint(img * (2**bits - 1)).astype(np.uint16)
    out = np.rint(img * 255.0).astype(np.uint8)
    if rng.random() < var.jpeg_p:
        q = int(rng.integers(var.jpeg_quality[0], var.jpeg_quality[1] + 1))
        _, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, q])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


@dataclass(frozen=True)
class CraterSetConfig:
    """Held-out and training images: scenes of ``scene`` through the camera of ``sensor``."""

    scene: SceneVariation = field(default_factory=SceneVariation)
    sensor: SensorVariation = field(default_factory=SensorVariation)
    min_label_px: float = 4.0
    min_listed_px: float = 2.0


@dataclass(frozen=True)
class CraterSample:
    """One labelled image: ``image`` (H, W) uint8 or uint16, ``labels`` and the ``scene`` it shows."""

    image: np.ndarray
    labels: CraterLabels
    scene: CraterScene
    scr: np.ndarray | None = None  # (K,) per label: photometric signal-to-clutter (NaN under 4 px; on request)


def scene_rng(seed: int, split: str, k: int) -> np.random.Generator:
    """The generator of scene ``k`` of ``split`` (disjoint streams per split)."""
    return np.random.default_rng([seed, SPLITS[split], 43, k])


def crater_scenes(n: int, seed: int, split: str = "train", var: SceneVariation = SceneVariation()) -> Iterator[CraterScene]:
    """``n`` seeded clean scenes (no camera) of ``split``."""
    for k in range(n):
        yield render_crater_scene(var, scene_rng(seed, split, k))


def crater_samples(n: int, seed: int, split: str = "eval", cfg: CraterSetConfig = CraterSetConfig(),
                   scr: bool = False) -> Iterator[CraterSample]:
    """``n`` labelled camera images of seeded scenes of ``split``; ``scr``: with each label's
    photometric signal-to-clutter ratio (the same images and labels; twice the shading and
    camera work)."""
    for k in range(n):
        rng = scene_rng(seed, split, k)
        scene = render_crater_scene(cfg.scene, rng, without_craters=scr)
        camera = copy.deepcopy(rng) if scr else None  # the same camera (draws and noise) for the ground
        image = orbital_sensor(scene.grey, rng, cfg.sensor)
        labels = crater_labels(scene.centres_px, scene.diameters_px, scene.visible, image.shape,
                               cfg.min_label_px, cfg.min_listed_px)
        ratio = None
        if scr:
            ground = orbital_sensor(scene.grey_without_craters, camera, cfg.sensor)
            ratio = signal_to_clutter(image, ground, labels.centres_px, labels.diameters_px)
        yield CraterSample(image, labels, scene, ratio)


SCR_DISC = 0.6  # signal: over the disc of this x the diameter (the bowl, the rim and its shadow)
SCR_WINDOW = 3.0  # clutter: over the square of this x the diameter a side


def signal_to_clutter(image: np.ndarray, ground: np.ndarray, centres_px: np.ndarray, diameters_px: np.ndarray,
                      min_px: float = 4.0) -> np.ndarray:
    """Per crater (K,): the rms of ``image - ground`` over the crater's disc (radius
    ``SCR_DISC`` D), over the std of ``ground`` in the square of side ``SCR_WINDOW`` D around it,
    both band-passed at the crater's scale (difference of Gaussians of sigma D / 16 and D / 2,
    D rounded to half octaves). ``image``: the camera image of a scene; ``ground``: the same
    camera on the same ground without craters. NaN for craters under ``min_px`` or without
    pixels in the image."""
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    a = np.asarray(image, np.float32) / np.float32(scale)
    g = np.asarray(ground, np.float32) / np.float32(scale)
    if a.shape != g.shape or a.ndim != 2:
        raise ValueError(f"signal_to_clutter: image {a.shape} and ground {g.shape} must be the same (H, W)")
    d = a - g
    H, W = a.shape
    c = np.reshape(np.asarray(centres_px, float), (-1, 2))
    D = np.ravel(np.asarray(diameters_px, float))
    out = np.full(len(D), np.nan)
    bins = np.where(D >= min_px, np.round(2.0 * np.log2(np.maximum(D, 1e-9))) / 2.0, np.nan)

    def band(x: np.ndarray, s: float) -> np.ndarray:
        return cv2.GaussianBlur(x, (0, 0), max(s / 16.0, 0.5)) - cv2.GaussianBlur(x, (0, 0), s / 2.0)

    for b in np.unique(bins[np.isfinite(bins)]):
        s = float(2.0**b)
        bd, bg = band(d, s), band(g, s)
        for i in np.flatnonzero(bins == b):
            (cx, cy), r, R = c[i], SCR_DISC * D[i], 0.5 * SCR_WINDOW * D[i]
            x0, x1, y0, y1 = int(max(cx - r, 0)), int(min(cx + r + 1, W)), int(max(cy - r, 0)), int(min(cy + r + 1, H))
            if x1 <= x0 or y1 <= y0:
                continue
            yy, xx = np.mgrid[y0:y1, x0:x1]
            disc = np.hypot(xx + 0.5 - cx, yy + 0.5 - cy) <= r
            X0, X1, Y0, Y1 = int(max(cx - R, 0)), int(min(cx + R + 1, W)), int(max(cy - R, 0)), int(min(cy + R + 1, H))
            if not disc.any() or X1 - X0 < 2 or Y1 - Y0 < 2:
                continue
            signal = float(np.sqrt(np.mean(bd[y0:y1, x0:x1][disc] ** 2)))
            out[i] = signal / max(float(np.std(bg[Y0:Y1, X0:X1])), 1e-9)
    return out

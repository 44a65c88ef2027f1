"""Rendered crater data sets for the orbital crater detector: cratered scenes
(:mod:`sim.crater_scene`) through an orbital camera model, with circle labels.

Labels: every crater whose centre lies in the image and whose rim is at least ``min_label_px``
across is a true crater, unless its bowl is hidden in the terrain's own relief
(:func:`sim.crater_scene.visible_craters`). Craters from ``min_listed_px`` up to that size,
hidden ones, and craters centred just outside the image whose rim reaches into it are *ignore*
craters: a detection on them is neither a true nor a false positive (COCO's "crowd" regions).
``train``, ``val`` (choice of the score threshold) and ``eval`` (the benchmark) draw from
disjoint seed streams, so evaluation worlds are never seen in training.

The camera (:func:`orbital_sensor`): atmospheric haze, optical blur, exposure, shot and read
noise, column striping and CCD-channel gain seams (HiRISE-like), quantisation to 8 bit or to
10-16 bit in a 16-bit container, and JPEG compression of some 8-bit products.
"""

from __future__ import annotations

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


def scene_rng(seed: int, split: str, k: int) -> np.random.Generator:
    """The generator of scene ``k`` of ``split`` (disjoint streams per split)."""
    return np.random.default_rng([seed, SPLITS[split], 43, k])


def crater_scenes(n: int, seed: int, split: str = "train", var: SceneVariation = SceneVariation()) -> Iterator[CraterScene]:
    """``n`` seeded clean scenes (no camera) of ``split``."""
    for k in range(n):
        yield render_crater_scene(var, scene_rng(seed, split, k))


def crater_samples(n: int, seed: int, split: str = "eval", cfg: CraterSetConfig = CraterSetConfig()) -> Iterator[CraterSample]:
    """``n`` labelled camera images of seeded scenes of ``split``."""
    for k in range(n):
        rng = scene_rng(seed, split, k)
        scene = render_crater_scene(cfg.scene, rng)
        image = orbital_sensor(scene.grey, rng, cfg.sensor)
        labels = crater_labels(scene.centres_px, scene.diameters_px, scene.visible, image.shape,
                               cfg.min_label_px, cfg.min_listed_px)
        yield CraterSample(image, labels, scene)

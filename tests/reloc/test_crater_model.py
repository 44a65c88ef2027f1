"""The shipped ONNX crater detector: it loads by default, is small, records how it was trained,
finds the craters of a seeded held-out rendered image within the stated errors, and gives the
same craters tiled as in one piece."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fgslam.bench.detect_craters import evaluate_craters, match_craters
from reloc.detector import CraterDetector, DetectorConfig, default_crater_model_path
from sim.crater_datasets import CraterSetConfig, crater_samples
from sim.crater_scene import SceneVariation


@pytest.fixture(scope="module")
def detector():
    return CraterDetector()


def test_shipped_crater_model_loads_and_records_its_training(detector):
    path = default_crater_model_path()
    assert path.is_file() and path.stat().st_size < 5e6
    assert detector.stride == 2 and detector.channels == 1 and 0.05 <= detector.score_threshold < 0.95
    meta = detector.session.get_modelmeta().custom_metadata_map
    info = json.loads(meta["train_info"])
    assert info["command"].startswith("python -m fgslam.train --kind crater") and "seed" in info and info["images"] > 0


def test_shipped_model_finds_craters_of_a_held_out_image(detector):
    samples = list(crater_samples(2, 11, "eval", CraterSetConfig(scene=SceneVariation(size_px=512))))
    dets = [detector.detect(s.image) for s in samples]
    labels = [s.labels for s in samples]
    r = evaluate_craters(dets, labels, detector.score_threshold, (8.0, np.inf))
    assert r["n_true"] >= 20
    # the shipped model is short of the goals (P 0.9, R 0.8, 0.1 D, 10 %; docs/detectors.md
    # has the measured table): these bounds guard what it reaches (0.50 / 0.50 / 0.15 D / 13 %)
    assert r["precision"] >= 0.4 and r["recall"] >= 0.4, r
    assert r["centre_error_d"] <= 0.2 and r["diameter_error"] <= 0.2, r


def test_tiled_inference_equals_whole_image_inference(detector):
    s = next(crater_samples(1, 12, "eval", CraterSetConfig(scene=SceneVariation(size_px=896))))
    whole = CraterDetector(config=DetectorConfig(tile=False)).detect(s.image)
    tiled = detector.detect(s.image)
    assert detector.levels(s.image.shape) >= 2 and len(whole) >= 20
    # every confident crater of the whole image is found tiled, at the same place and size
    strong = whole.select(whole.score >= detector.score_threshold + 0.1)
    d = np.linalg.norm(strong.centers_px[:, None] - tiled.centers_px[None], axis=2)
    j = d.argmin(axis=1)
    same = ((d[np.arange(len(strong)), j] <= 0.05 * strong.diameters_px + 0.25)
            & (np.abs(tiled.diameters_px[j] / strong.diameters_px - 1.0) <= 0.03)
            & (np.abs(tiled.score[j] - strong.score) <= 0.05))
    assert np.mean(same) >= 0.9, np.mean(same)  # the rest differ only near tile seams
    assert abs(len(tiled) - len(whole)) <= max(2, 0.1 * len(whole))  # near-threshold ones come and go
    m, _ = match_craters(tiled, s.labels, 0.5)
    assert np.sum(m == 1) >= 0.5 * np.sum(~s.labels.ignore & (s.labels.diameters_px >= 8))

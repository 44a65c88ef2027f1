"""The shipped ONNX rock detectors: they load by default, are small, and find rocks on rendered
held-out scenes; ``fgslam catalog`` turns a nadir image into a catalog of true rock positions."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from fgslam.bench.detect import match_image
from reloc.detector import RockDetector, default_model_path
from sim.datasets import NadirSetConfig, nadir_samples, rover_samples


@pytest.mark.parametrize("kind", ["nadir", "rover"])
def test_shipped_model_loads_and_is_small(kind):
    path = default_model_path(kind)
    assert path.is_file(), f"shipped {kind} model missing: {path}"
    assert path.stat().st_size < 10e6
    det = RockDetector(kind=kind)
    assert det.layout == "centernet-v1" and det.channels == 1
    assert 0.05 <= det.score_threshold < 0.95
    assert det.tile == (kind == "nadir")


def _pr(dets, labels) -> tuple[float, float]:
    tp = fp = n_gt = 0
    for d, lab in zip(dets, labels):
        m = match_image(d.boxes_xyxy, d.score, lab.positives, lab.boxes_xyxy[lab.ignore], 0.5)
        tp += int(np.sum(m == 1))
        fp += int(np.sum(m == 0))
        n_gt += len(lab.positives)
    return tp / max(tp + fp, 1), tp / max(n_gt, 1)


def test_nadir_model_finds_rocks_on_a_held_out_tile():
    det = RockDetector(kind="nadir")
    samples = list(nadir_samples(1, 7, "eval", NadirSetConfig(tile_px=384)))
    assert len(samples[0].labels.positives) >= 10
    p, r = _pr([det.detect(s.image) for s in samples], [s.labels for s in samples])
    assert p >= 0.6 and r >= 0.5, (p, r)


def test_rover_model_finds_rocks_on_held_out_views():
    det = RockDetector(kind="rover")
    samples = list(rover_samples(3, 7, "eval"))
    assert sum(len(s.labels.positives) for s in samples) >= 10
    p, r = _pr([det.detect(s.image) for s in samples], [s.labels for s in samples])
    assert p >= 0.7 and r >= 0.6, (p, r)


def test_catalog_command_maps_pixels_to_world(tmp_path):
    import cv2

    from fgslam.cli import app
    from fgslam.io.catalog_csv import read_catalog_csv

    s = next(nadir_samples(1, 11, "eval", NadirSetConfig(tile_px=384, gsd_m=(0.05, 0.05))))
    png = tmp_path / "nadir.png"
    cv2.imwrite(str(png), s.image)
    xmin, _, _, ymax = s.nadir.extent
    out = tmp_path / "catalog.csv"
    res = CliRunner().invoke(app, ["catalog", str(png), "--gsd", "0.05", "--origin", str(xmin), str(ymax), "--out", str(out)])
    assert res.exit_code == 0, res.output
    cat = read_catalog_csv(out)
    assert len(cat) >= 5
    rocks = s.world.rocks
    big = rocks.size_m >= 0.2
    dist = np.linalg.norm(cat.xy_m[:, None] - rocks.xyz_m[None, big, :2], axis=2)
    near = dist.min(axis=1)
    assert np.mean(near < 0.15) >= 0.7
    j = dist.argmin(axis=1)[near < 0.15]
    assert 0.6 < np.median(cat.size_m[near < 0.15] / rocks.size_m[big][j]) < 1.6
    bad = CliRunner().invoke(app, ["catalog", str(tmp_path / "none.png"), "--gsd", "0.05", "--out", str(out)])
    assert bad.exit_code != 0

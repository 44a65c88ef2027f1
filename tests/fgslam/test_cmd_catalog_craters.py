"""``fgslam catalog --landmark crater``: a crater catalog in world metres from a rendered image in
any bit depth and file format, and clear errors for bad inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fgslam.cli import main
from fgslam.io.catalog_csv import read_catalog_csv
from sim.crater_datasets import CraterSetConfig, crater_samples
from sim.crater_scene import SceneVariation

GSD_M = 0.5
ORIGIN = (1000.0, 2000.0)


@pytest.fixture(scope="module")
def sample():
    return next(crater_samples(1, 3, "eval", CraterSetConfig(scene=SceneVariation(size_px=384))))


def _run(args, capsys):
    rc = main(args)
    return rc, capsys.readouterr().err


def _grey8(sample) -> np.ndarray:
    img = sample.image
    return img if img.dtype == np.uint8 else np.rint(img / img.max() * 255).astype(np.uint8)


def test_crater_catalog_in_world_metres(tmp_path, sample, capsys):
    png = tmp_path / "orbital.png"
    cv2.imwrite(str(png), _grey8(sample))
    out = tmp_path / "craters.csv"
    rc, err = _run(["catalog", str(png), "--gsd", str(GSD_M), "--origin", *map(str, ORIGIN), "--landmark", "crater",
                    "--out", str(out)], capsys)
    assert rc == 0, err
    assert out.read_text().splitlines()[0] == "x,y,size,score"
    cat = read_catalog_csv(out)
    centres, diam = sample.labels.positives
    big = diam >= 8
    assert big.sum() >= 4 and len(cat) >= 0.4 * big.sum()
    # the image's pixel (u, v) is at (x0 + u gsd, y0 - v gsd); size is the rim diameter in metres
    true_xy = np.column_stack([ORIGIN[0] + centres[big, 0] * GSD_M, ORIGIN[1] - centres[big, 1] * GSD_M])
    true_d = diam[big] * GSD_M
    dist = np.linalg.norm(cat.xy_m[:, None] - true_xy[None], axis=2) / true_d[None]
    j = dist.argmin(axis=1)
    near = dist[np.arange(len(cat)), j] < 0.25
    assert near.sum() >= 0.4 * big.sum()  # the shipped model's recall is about 0.5
    assert np.median(np.abs(cat.size_m[near] / true_d[j[near]] - 1.0)) < 0.2
    assert f"{len(cat)} craters" in err


def test_bit_depths_and_formats_give_the_same_catalog(tmp_path, sample, capsys):
    tifffile = pytest.importorskip("tifffile")
    g8 = _grey8(sample)
    paths = {"png8": tmp_path / "a.png", "png16": tmp_path / "b.png", "tif16": tmp_path / "c.tif", "tif32": tmp_path / "d.tif"}
    cv2.imwrite(str(paths["png8"]), g8)
    cv2.imwrite(str(paths["png16"]), g8.astype(np.uint16) * 257)
    tifffile.imwrite(str(paths["tif16"]), g8.astype(np.uint16) * 64)  # 14-bit data
    f = g8.astype(np.float32) / 255.0 * 0.2 + 0.05  # reflectance-like floats
    f[:5] = np.nan  # a nodata strip
    tifffile.imwrite(str(paths["tif32"]), f)
    cats = {}
    for name, p in paths.items():
        out = tmp_path / f"{name}.csv"
        rc, err = _run(["catalog", str(p), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
        assert rc == 0, err
        cats[name] = read_catalog_csv(out)
    ref = cats["png8"]
    for name, cat in cats.items():
        assert abs(len(cat) - len(ref)) <= max(2, 0.1 * len(ref)), name
        d = np.linalg.norm(cat.xy_m[:, None] - ref.xy_m[None], axis=2).min(axis=1)
        assert np.mean(d < 1.0) >= 0.8, name


def test_image_without_craters_writes_no_unusable_catalog(tmp_path, capsys):
    """A catalog `fgslam run` would reject (fewer than 3 entries) is an error, and no file."""
    flat = np.tile(np.linspace(90, 140, 256), (256, 1)).astype(np.uint8)  # a smooth slope, no crater
    png = tmp_path / "flat.png"
    cv2.imwrite(str(png), flat)
    out = tmp_path / "none.csv"
    rc, err = _run(["catalog", str(png), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
    assert rc == 2 and "0 craters detected, a catalog needs at least 3" in err
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--gsd", "0"], "--gsd must be a finite ground sample distance > 0"),
    (["--gsd", "-2"], "--gsd must be a finite ground sample distance > 0"),
    (["--gsd", "nan"], "--gsd must be a finite ground sample distance > 0"),
    (["--gsd", "1", "--landmark", "boulder"], "--landmark must be one of rock, crater, got 'boulder'"),
    (["--gsd", "1", "--landmark", "rock", "--nodata", "0"], "--nodata applies to --landmark crater only"),
    (["--gsd", "1", "--landmark", "crater", "--score-threshold", "1.5"], "--score-threshold must be in [0, 1]"),
])
def test_bad_arguments(tmp_path, capsys, args, message):
    png = tmp_path / "img.png"
    cv2.imwrite(str(png), np.zeros((64, 64), np.uint8))
    out = tmp_path / "x.csv"
    rc, err = _run(["catalog", str(png), "--out", str(out), *args], capsys)
    assert rc == 2 and message in err and not out.exists()


def test_bad_image_files(tmp_path, capsys):
    out = tmp_path / "x.csv"
    rc, err = _run(["catalog", str(tmp_path / "missing.png"), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
    assert rc == 2 and "image file not found" in err
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image at all")
    rc, err = _run(["catalog", str(junk), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
    assert rc == 2 and "not an image OpenCV can read" in err
    bad_tif = tmp_path / "junk.tif"
    bad_tif.write_bytes(b"II*\x00garbage")
    rc, err = _run(["catalog", str(bad_tif), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
    assert rc == 2 and "not a readable TIFF" in err
    nan_tif = tmp_path / "nan.tif"
    pytest.importorskip("tifffile").imwrite(str(nan_tif), np.full((64, 64), np.nan, np.float32))
    rc, err = _run(["catalog", str(nan_tif), "--gsd", "1", "--landmark", "crater", "--out", str(out)], capsys)
    assert rc == 2 and "no valid pixel" in err
    assert not out.exists()


def test_bench_detect_rejects_an_unknown_landmark(capsys):
    rc, err = _run(["bench", "detect", "--landmark", "boulder"], capsys)
    assert rc == 2 and "--landmark must be one of rock, crater, got 'boulder'" in err


def test_bench_detect_craters_reports_the_signal_to_clutter_rows(tmp_path, capsys):
    import json

    out = tmp_path / "bench"
    rc, err = _run(["bench", "detect", "--landmark", "crater", "--quick", "--out", str(out)], capsys)
    assert rc == 0, err
    res = json.loads((out / "results.json").read_text())
    goal_row, bins, visible = res["rows"][">= 8 px (goal)"], res["scr_rows"], res["visible_row"]
    # the bins split the goal row's true craters (those with a ratio; none under 8 px is NaN)
    assert sum(r["n_true"] for r in bins.values()) == goal_row["n_true"] > 0
    assert visible["n_true"] == sum(r["n_true"] for name, r in bins.items() if float(name.split()[1].split("-")[0]) >= 2.0)
    assert "signal-to-clutter" in (out / "table.md").read_text()

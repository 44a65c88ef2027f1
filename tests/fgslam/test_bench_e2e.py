"""``fgslam bench e2e`` on a very short traverse: both detection sources through both back-ends,
every output written, errors finite and small, bad arguments named."""

from __future__ import annotations

import json
import math

import pytest

from fgslam.cli import main

VARIANTS = ("ekf", "ekf_reloc", "isam2", "isam2_reloc")


def test_bench_e2e_runs_both_sources_through_both_backends(tmp_path, capsys):
    out = tmp_path / "e2e"
    rc = main(["bench", "e2e", "--world", "my2022", "--seed", "1", "--distance-m", "3", "--out", str(out)])
    assert rc == 0
    for name in ("table.md", "results.json", "statistical/bag/metadata.yaml", "image/bag/metadata.yaml",
                 "image/catalog.csv", "compare/results.json"):
        assert (out / name).is_file(), name
    res = json.loads((out / "results.json").read_text())
    assert set(res["sources"]) == {"statistical", "image"} and res["stereo_rate_hz"] == 0.5
    for source, entry in res["sources"].items():
        runs = entry["comparison"]["runs"]
        for k in VARIANTS:
            ate = runs[k]["ate"]["rmse"]
            assert math.isfinite(ate) and ate < 0.3, (source, k, ate)
        det = entry["detections"]
        assert det["n_stereo_frames"] >= 15 and det["n_detections"] > 0 and det["stereo_precision"] > 0.5
    img, stat = res["sources"]["image"], res["sources"]["statistical"]
    # one simulated run: same frames, same odometry, so the same dead-reckoning error
    assert img["detections"]["n_stereo_frames"] == stat["detections"]["n_stereo_frames"]
    assert img["comparison"]["runs"]["dead_reckoning"]["ate"]["rmse"] == pytest.approx(
        stat["comparison"]["runs"]["dead_reckoning"]["ate"]["rmse"])
    # the image path's own figures: its catalog comes from the nadir detector, its timings are measured
    assert img["detections"]["n_catalog"] != stat["detections"]["n_catalog"]
    assert img["detections"]["image_render_s_per_frame"] > 0 and stat["detections"]["image_render_s_per_frame"] is None
    table = (out / "table.md").read_text()
    assert "| EKF ATE [m] |" in table and "| iSAM2 + reloc ATE [m] |" in table
    assert "statistical" in capsys.readouterr().out


@pytest.mark.parametrize("args, option", [
    (["--distance-m", "0"], "--distance-m"),
    (["--stereo-rate-hz", "-1"], "--stereo-rate-hz"),
    (["--world", "my2099"], "--world"),
])
def test_bench_e2e_rejects_bad_arguments(tmp_path, capsys, args, option):
    rc = main(["bench", "e2e", "--out", str(tmp_path / "x"), *args])
    assert rc != 0
    assert option in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # rejected before any work

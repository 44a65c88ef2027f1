"""``fgslam match`` on small CSVs, and a tiny ``fgslam bench match`` run read back from its files."""

from __future__ import annotations

import json

import numpy as np

from fgslam.cli import main


def _write_csv(path, xy, size):
    lines = ["x,y,size,score"] + [f"{x:.4f},{y:.4f},{s:.4f},0.9" for (x, y), s in zip(xy, size)]
    path.write_text("\n".join(lines) + "\n")


def _scene(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 40, (480, 2))  # 0.3 rocks / m^2
    size = rng.lognormal(np.log(0.3), 0.5, 480)
    center = np.array([20.0, 20.0])
    idx = np.argsort(np.hypot(*(xy - center).T))[:40]
    keep = idx[rng.random(40) >= 0.3]
    theta, t = 0.8, np.array([5.0, -3.0])
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    local = (xy[keep] + rng.normal(0, 0.03, (keep.size, 2)) - t) @ rot
    return xy, size, local, size[keep], theta, t


def test_match_json_recovers_the_transform(tmp_path, capsys):
    xy, size, local, lsize, theta, t = _scene(1)
    _write_csv(tmp_path / "cat.csv", xy, size)
    _write_csv(tmp_path / "local.csv", local, lsize)
    rc = main(["match", "--catalog", str(tmp_path / "cat.csv"), "--local", str(tmp_path / "local.csv"),
               "--json", "--seed", "2", "--sigma", "0.05"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["match"] is True
    assert abs(out["rotation_rad"] - theta) < np.radians(1.0)
    np.testing.assert_allclose(out["translation"], t, atol=0.2)
    assert out["n_inliers"] >= 20 and len(out["inlier_pairs"]) == out["n_inliers"]
    assert np.array(out["transform_cov"]).shape == (3, 3)


def test_match_reports_no_match_with_exit_1(tmp_path, capsys):
    xy, size, *_ = _scene(1)
    _, _, local, lsize, *_ = _scene(2)  # a map of another field
    _write_csv(tmp_path / "cat.csv", xy, size)
    _write_csv(tmp_path / "local.csv", local, lsize)
    rc = main(["match", "--catalog", str(tmp_path / "cat.csv"), "--local", str(tmp_path / "local.csv"), "--json"])
    assert rc == 1
    assert json.loads(capsys.readouterr().out)["match"] is False


def test_match_bad_csv_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "cat.csv").write_text("x,y,size\n1,2\n")
    (tmp_path / "local.csv").write_text("x,y,size\n1,2,0.3\n")
    rc = main(["match", "--catalog", str(tmp_path / "cat.csv"), "--local", str(tmp_path / "local.csv")])
    assert rc == 2
    assert "cat.csv" in capsys.readouterr().err


def test_bench_match_tiny_run_writes_tables(tmp_path):
    rc = main(["bench", "match", "--sizes", "300", "--layouts", "uniform", "--sigmas", "0.05", "--queries", "6",
               "--outside-queries", "4", "--detector-queries", "0", "--astro-queries", "0", "--build-size", "2000",
               "--out", str(tmp_path)])
    assert rc in (0, None)
    res = json.loads((tmp_path / "results.json").read_text())
    known = res["known"][0]
    assert known["queries"] == 6 and known["success_pct"] >= 80.0
    assert res["outside"][0]["false_matches"] == 0
    assert res["build"][0]["rocks"] == 2000 and res["build"][0]["build_s"] > 0
    table = (tmp_path / "table.md").read_text()
    assert "| 300 | uniform | 0.05 | 6 |" in table

"""`fgslam bench ekf` smoke test: the cost curve runs and its results.json reads back."""

from __future__ import annotations

import json
import subprocess
import sys


def test_bench_ekf_cost_curve_writes_results(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "fgslam", "bench", "ekf", "--skip-traverse", "--curve", "0,25", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "per-step cost" in proc.stdout
    res = json.loads((tmp_path / "results.json").read_text())
    points = {p["n_landmarks"]: p for p in res["cost_curve"]}
    assert set(points) == {0, 25}
    # pose, the yaw-rate bias and the slip, the rock and crater fixes' shared offsets, the landmarks
    assert points[25]["state_dim"] == 6 + 2 + 2 * 3 + 3 * 25
    assert 0 < points[0]["predict_ms"] < 50 and 0 < points[25]["frame_ms"] < 500

"""The kilometre drift table (``python -m sim.tiled.bench drift``) on what `fgslam run` writes today."""

from __future__ import annotations

import numpy as np

import fgslam
from sim.tiled.bench import drift, drift_rows
from tests.fgslam._synth_stream import make_stream, write_input_dir


def test_the_drift_table_reads_a_run_directory_against_the_bags_truth(tmp_path, capsys):
    inputs = make_stream(seed=2, duration_s=40.0)
    sim_dir = write_input_dir(tmp_path / "sim", inputs)
    out = fgslam.run(sim_dir, backend="ekf", reloc=False, out=tmp_path / "ekf")
    (row,) = drift_rows(sim_dir, [tmp_path / "ekf"])

    truth = [m for m in inputs.measurements if type(m).__name__ == "GroundTruthPose"]
    xy = np.array([m.position_m[:2] for m in truth])
    assert abs(row["distance_m"] - np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) < 0.05
    final = out.result.final.positions_m[-1, :2]
    assert abs(row["final_error_m"] - np.linalg.norm(final - xy[-1])) < 0.01
    assert row["drift_pct"] == 100 * row["final_error_m"] / row["distance_m"]
    assert row["final_error_m"] <= row["max_error_m"]
    assert row["ate_m"] == out.metrics["ate"]["rmse"] and row["backend"] == "ekf"
    assert row["nees_verdict"] in ("consistent", "optimistic", "pessimistic") and row["peak_rss_mb"] > 0
    drift(sim_dir, [tmp_path / "ekf"])
    assert "| ekf | ekf |" in capsys.readouterr().out

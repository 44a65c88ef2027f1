"""The comparison recording: read the .rrd back and check entities, timeline and blueprint."""

from __future__ import annotations

import numpy as np
import pytest
from _synth_stream import NearestNeighbourMatcher, make_stream

from fgslam.compare import CompareConfig, compare_world
from fgslam.relocalizer import Relocalizer
from fgslam.viz import rerun_log


@pytest.fixture(scope="module")
def comparison():
    inputs = make_stream(seed=5, duration_s=40.0)
    cfg = CompareConfig(backends=("dr",), reference_backend="dr", backend_overrides={"dr": {"use_fixes": True}}, workers=1)
    reloc = Relocalizer(inputs.catalog, cfg.relocalizer, matcher=NearestNeighbourMatcher(inputs.catalog.xy_m))
    return compare_world(inputs, cfg, relocalizers=[reloc])


def test_recording_holds_entities_timeline_and_blueprint(tmp_path, comparison):
    from rerun.chunk import RrdReader

    path = rerun_log.write_comparison_rrd(tmp_path / "compare.rrd", [comparison])
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1
    chunks = list(reader.stream())
    paths = {c.entity_path for c in chunks}
    w = "/" + comparison.inputs.name
    for key in ("dr", "dr_reloc"):
        for ent in (rerun_log.ENT_PATH, rerun_log.ENT_POSE, rerun_log.ENT_POSE_COV, f"{rerun_log.ENT_LANDMARKS}/rocks"):
            assert f"{w}/{key}/{ent}" in paths
        assert f"{w}/{rerun_log.ENT_ERR_POS}/{key}" in paths
        assert f"{w}/{rerun_log.ENT_ERR_POS}/{key}_3sigma" in paths
        assert f"{w}/{rerun_log.ENT_ERR_YAW}/{key}" in paths
    for ent in (f"{rerun_log.ENT_CATALOG}/rocks", rerun_log.ENT_TRUTH, rerun_log.ENT_TRUTH_POSE,
                rerun_log.ENT_MATCHES):
        assert f"{w}/{ent}" in paths
    assert any(q.startswith(f"{w}/{rerun_log.ENT_ORBITAL}/") for q in paths)  # the image's tiles
    assert f"{w}/dr_reloc/{rerun_log.ENT_FIXES}" in paths  # fix events of the run that received fixes
    # static map, time-varying estimate on the sim_time timeline
    by_path = {}
    for c in chunks:
        by_path.setdefault(c.entity_path, []).append(c)
    assert all(c.is_static for c in by_path[f"{w}/{rerun_log.ENT_CATALOG}/rocks"])
    pose_chunks = by_path[f"{w}/dr_reloc/{rerun_log.ENT_POSE}"]
    assert all(rerun_log.TIMELINE in c.timeline_names for c in pose_chunks)
    on = comparison.runs["dr_reloc"].online
    n_on = len(rerun_log.path_samples(on.t, on.positions_m))  # one sample per 1 m of path
    assert 10 < n_on < len(on)
    assert sum(c.num_rows for c in pose_chunks) == n_on
    err_rows = sum(c.num_rows for c in by_path[f"{w}/{rerun_log.ENT_ERR_POS}/dr_reloc"] if not c.is_static)
    assert err_rows == n_on
    # the blueprint is saved with the recording and has views
    bps = reader.blueprints()
    assert len(bps) == 1
    views = {}
    bp_paths = set()
    for c in reader.stream(store=bps[0]):
        bp_paths.add(c.entity_path)
        if c.entity_path.startswith("/view/") and c.entity_path.count("/") == 2:
            rb = c.to_record_batch()
            cols = {n.split(":")[-1]: rb.column(i).to_pylist()[0][0] for i, n in enumerate(rb.schema.names) if ":" in n}
            views[cols["display_name"]] = (cols["class_identifier"], cols["space_origin"])
    name = comparison.inputs.name
    assert views[f"{name}: Dead reckoning + reloc"] == ("3D", w)  # one map view per variant with fixes
    assert views["position error [m] and 3σ"] == ("TimeSeries", f"{w}/{rerun_log.ENT_ERR_POS}")
    assert views["yaw error [deg] and 3σ"] == ("TimeSeries", f"{w}/{rerun_log.ENT_ERR_YAW}")
    assert "/viewport" in bp_paths


def test_ellipses_are_three_sigma_and_rotated():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 9.0]]])
    half, q = rerun_log.ellipses(cov)
    assert np.allclose(np.sort(half[0, :2]), [3.0, 6.0])
    assert np.allclose(np.sort(half[1, :2]), [3.0, 9.0])
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    # the largest axis of the second ellipse lies along y: eigenvector angle +-90 deg
    big = int(np.argmax(half[1, :2]))
    ang = 2 * np.arctan2(q[1, 2], q[1, 3])
    axis = np.array([np.cos(ang), np.sin(ang)]) if big == 0 else np.array([-np.sin(ang), np.cos(ang)])
    assert abs(abs(axis[1]) - 1.0) < 1e-9


def test_map_landmarks_are_discs_of_their_three_sigma_major_axis():
    from fgslam.viz.landmarks import three_sigma_radius

    c = np.zeros((2, 3, 3))
    c[0, :2, :2] = [[4.0, 0.0], [0.0, 1.0]]
    c[1, :2, :2] = [[2.0, 1.0], [1.0, 2.0]]  # eigenvalues 1 and 3, rotated 45 deg
    c[:, 2, 2] = 100.0  # the height's variance is not the disc's
    assert np.allclose(three_sigma_radius(c), [6.0, 3.0 * np.sqrt(3.0)])


def test_path_samples_every_metre_or_ten_seconds():
    t = np.arange(0.0, 100.0, 0.1)
    xy = np.column_stack([0.05 * t, np.zeros_like(t)])  # 0.05 m/s: 1 m every 20 s, so every 10 s
    xy[t > 50.0, 0] = 2.5  # standing still after 50 s
    k = rerun_log.path_samples(t, xy)
    assert k[0] == 0 and k[-1] == len(t) - 1
    d = np.diff(t[k])
    assert np.all(d <= 10.0 + 1e-9) and len(k) <= 12

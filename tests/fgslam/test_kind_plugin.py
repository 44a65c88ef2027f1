"""A landmark kind added by registration only: the toy kind "cairns" (tests/toykind, one module per
layer) goes through the bag writer and reader, the runner, the EKF (update and history replay),
the smoother (factors, key symbol, fixed-lag marginalization), dead reckoning, its own
relocalizer alone or beside the rocks', the comparison's config and the rerun recording, without
an edit of any of them."""

from __future__ import annotations

import numpy as np
import pytest
from _synth_stream import NearestNeighbourMatcher, make_stream

from fgslam import metrics as M
from fgslam.backends.registry import make_backend, resolved_config
from fgslam.fix_sources import OnlineFixes, ReplayedFixes
from fgslam.inputs import RunInputs, truth_of
from fgslam.relocalizer import Relocalizer, RelocalizerConfig
from fgslam.runner import run_backend
from reloc.errors import ConfigError
from reloc.kinds import kind_named, kinds_with, registered
from reloc.measurements import GlobalFix, RockObservations, sort_key
from tests.toykind import CAIRNS
from tests.toykind.measurement import CairnObservations
from tests.toykind.relocalizer import CairnCatalog, CairnRelocalizer, write_cairn_csv

SIGMA_M = 0.02


@pytest.fixture(scope="module")
def cairns():
    with registered(CAIRNS):
        yield CAIRNS


def _with_cairns(base: RunInputs, seed: int, rocks: bool = True) -> tuple[RunInputs, np.ndarray]:
    """``base`` plus cairn frames (2 Hz, within 10 m ahead) and a cairn catalog; optionally without rocks."""
    rng = np.random.default_rng(seed)
    gt = truth_of(base)
    lo, hi = gt.positions_m[:, :2].min(0) - 6.0, gt.positions_m[:, :2].max(0) + 6.0
    true_xy = rng.uniform(lo, hi, (40, 2))
    height = rng.uniform(0.5, 1.5, len(true_xy))
    frames = []
    for k in range(0, len(gt), 15):
        T = gt.T_world_base[k]
        local = (np.column_stack([true_xy, np.zeros(len(true_xy))]) - T[:3, 3]) @ T[:3, :3]
        vis = (local[:, 0] > 0.5) & (np.linalg.norm(local, axis=1) < 10.0) & (np.abs(np.arctan2(local[:, 1], local[:, 0])) < 1.0)
        m = int(vis.sum())
        frames.append(CairnObservations(float(gt.t[k]), local[vis] + rng.normal(0, SIGMA_M, (m, 3)),
                                        np.tile(np.eye(3) * SIGMA_M**2, (m, 1, 1)), height[vis]))
    meas = [m for m in base.measurements if rocks or not isinstance(m, RockObservations)] + frames
    meas.sort(key=sort_key)
    catalog = CairnCatalog(true_xy + rng.normal(0, 0.02, true_xy.shape), height)
    cats = {"cairns": catalog, **({"rocks": base.catalogs["rocks"]} if rocks else {})}
    return RunInputs(base.name, meas, cats, base.initial, base.orbital_image, base.orbital_extent,
                     base.rocks_true_xy), true_xy


@pytest.fixture(scope="module")
def world(cairns):
    return _with_cairns(make_stream(seed=11, duration_s=60.0), seed=1)


def _map_error(lmap, true_xy) -> np.ndarray:
    return np.array([np.min(np.linalg.norm(true_xy - p[:2], axis=1)) for p in lmap.xyz_world_m])


def test_the_kind_lives_in_its_own_modules(cairns):
    assert kind_named("cairns") is CAIRNS and CAIRNS in kinds_with("smoother")
    for layer in ("measurement", "bag", "ekf", "smoother", "relocalizer", "catalog", "rerun"):
        ref = getattr(CAIRNS, layer)
        assert ref.startswith("tests.toykind."), ref
        assert CAIRNS.layer(layer) is not None
    # the same stamp: motion first, rocks, then cairns
    t = 1.0
    rock = RockObservations(t, np.zeros((0, 3)), np.zeros((0, 3, 3)), [], [])
    cairn = CairnObservations(t, np.zeros((0, 3)), np.zeros((0, 3, 3)), [])
    assert sorted([cairn, rock], key=sort_key) == [rock, cairn]


def test_cairns_travel_through_a_bag(tmp_path, world, cairns):
    from rosbags.highlevel import AnyReader

    from fgslam.io.bag_reader import read_bag
    from sim.bag_writer import write_bag

    inputs, _ = world
    write_bag(tmp_path / "bag", inputs.measurements)
    stream = read_bag(tmp_path / "bag")
    want = [m for m in inputs.measurements if isinstance(m, CairnObservations)]
    got = stream.of_type(CairnObservations)
    assert len(got) == len(want) and stream.report.topics["/cairns"].role == "cairns"
    for a, b in zip(got, want):
        assert a.t == pytest.approx(b.t, abs=1e-9)
        np.testing.assert_allclose(a.xyz_base_m, b.xyz_base_m)
        np.testing.assert_allclose(a.cov_base_m2, b.cov_base_m2)
        np.testing.assert_allclose(a.size_m, b.size_m)
    assert len(stream.of_type(RockObservations)) == sum(isinstance(m, RockObservations) for m in inputs.measurements)
    with AnyReader([tmp_path / "bag"]) as reader:  # an independent reader sees the topic
        assert reader.topics["/cairns"].msgtype == "vision_msgs/msg/Detection3DArray"
        assert reader.topics["/cairns"].msgcount == len(want)
    # reading only the rocks leaves the cairns out
    assert read_bag(tmp_path / "bag", kinds=["rocks"]).of_type(CairnObservations) == []


@pytest.mark.parametrize("name, tol_m", [("ekf", 0.15), ("isam2", 0.15), ("dr", 1.5)])
def test_every_backend_maps_the_cairns_beside_the_rocks(world, cairns, name, tol_m):
    inputs, true_xy = world
    res = run_backend(make_backend(name, inputs.initial), inputs.measurements)
    assert set(res.landmarks) == {"rocks", "cairns"}
    cm = res.landmarks["cairns"]
    assert cm.kind == "cairns" and len(cm) >= 10 and res.landmarks["rocks"].kind == "rocks"
    assert np.median(_map_error(cm, true_xy)) < tol_m
    # each kind's map holds its own: the rocks near true rocks, none of them on a cairn
    rm = res.landmarks["rocks"]
    assert len(rm) > 20 and np.median(_map_error(rm, inputs.rocks_true_xy)) < tol_m
    assert np.min([np.min(np.linalg.norm(true_xy - p[:2], axis=1)) for p in rm.xyz_world_m]) > 0.05


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_fixes_from_the_cairn_catalog_correct_a_wrong_start(cairns, name):
    """Started 0.4 m and 2 deg off (inside its covariance), SLAM on cairns alone keeps the offset;
    the cairn relocalizer's fixes bring the back-end onto the catalog's frame."""
    from reloc.backend import PoseEstimate
    from reloc.geometry import exp_so3

    inputs, _ = _with_cairns(make_stream(seed=12, duration_s=60.0), seed=2, rocks=False)
    gt = truth_of(inputs)
    T = inputs.initial.T_world_base.copy()
    T[:3, :3] = exp_so3(np.array([0.0, 0.0, np.radians(2.0)])) @ T[:3, :3]
    T[:2, 3] += [0.4, -0.2]
    start = PoseEstimate(inputs.initial.t, T, np.diag([0.3**2, 0.3**2, 0.01**2, 1e-6, 1e-6, np.radians(3.0) ** 2]))
    reloc = CairnRelocalizer(inputs.catalogs["cairns"], {"period_s": 4.0})
    res = run_backend(make_backend(name, start), inputs.measurements, OnlineFixes([reloc]))
    base = run_backend(make_backend(name, start), inputs.measurements)
    fixes = [a.fix for a in res.attempts if a.fix is not None]
    assert len(fixes) >= 8 and all(a.source == "cairns" for a in res.attempts)
    assert sum(o.accepted for o in res.outcomes) >= 0.8 * len(res.outcomes)
    assert set(res.landmarks) == {"cairns"}
    err, _ = M.fix_errors(np.array([f.xyyaw for f in fixes]), np.array([f.t_meas for f in fixes]), gt)
    assert np.median(err) < 0.1
    assert M.ate(base.final, gt).rmse > 0.3
    assert M.ate(res.online, gt).rmse < 0.5 * M.ate(base.online, gt).rmse
    tail = res.online.t > 40.0  # after a few fixes the estimate sits on the catalog's frame
    assert np.max(np.linalg.norm(res.online.positions_m[tail, :2] - _truth_xy(gt, res.online.t[tail]), axis=1)) < 0.1


def _truth_xy(gt, t) -> np.ndarray:
    return np.column_stack([np.interp(t, gt.t, gt.positions_m[:, k]) for k in range(2)])


def test_rocks_and_cairns_relocalize_side_by_side(world, cairns):
    inputs, _ = world
    rocks = Relocalizer(inputs.catalogs["rocks"], RelocalizerConfig(period_s=4.0, delay_s=1.0),
                        matcher=NearestNeighbourMatcher(inputs.catalogs["rocks"].xy_m))
    both = OnlineFixes([rocks, CairnRelocalizer(inputs.catalogs["cairns"])])
    res = run_backend(make_backend("ekf", inputs.initial), inputs.measurements, both)
    by_source = {s: sum(a.fix is not None for a in res.attempts if a.source == s) for s in ("rocks", "cairns")}
    assert by_source["rocks"] >= 5 and by_source["cairns"] >= 5
    assert [a.t_meas for a in res.attempts] == sorted(a.t_meas for a in res.attempts)
    assert all(o.accepted for o in res.outcomes)


def test_the_ekf_replays_cairn_frames_after_a_late_fix(world, cairns):
    inputs, _ = world
    gt = truth_of(inputs)
    fixes = []
    for t in (15.0, 30.0, 45.0):
        T = gt.T_world_base[np.searchsorted(gt.t, t)]
        fixes.append(GlobalFix(t, t + 6.0, T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])), np.eye(3) * 1e-3))
    ekf = make_backend("ekf", inputs.initial)
    res = run_backend(ekf, inputs.measurements, ReplayedFixes(fixes))
    extra = ekf.stats().extra
    assert all(o.accepted for o in res.outcomes) and extra["n_late_fixes"] == 3 and extra["n_replayed_entries"] > 0
    # counters count each cairn detection once, however often its frame was replayed
    n_det = sum(len(m) for m in inputs.measurements if isinstance(m, CairnObservations))
    assert extra["n_cairns_associated"] + extra["n_cairns_new"] == n_det


def test_the_fixed_lag_smoother_marginalizes_cairns(world, cairns):
    inputs, true_xy = world
    sm = make_backend("isam2", inputs.initial, {"fixed_lag_s": 10.0})
    res = run_backend(sm, inputs.measurements)
    layer = sm.kinds.get("cairns")
    assert layer.n_marginalized > 5 and sm.stats().extra["n_cairns_marginalized"] == layer.n_marginalized
    assert np.median(_map_error(res.landmarks["cairns"], true_xy)) < 0.15  # retired ones stay in the map


def test_kind_settings_are_resolved_overridden_and_checked(world, cairns):
    from ekf.errors import EkfInputError
    from fgslam.errors import SmootherError

    assert resolved_config("ekf")["kinds"]["cairns"] == {"gate_chi2": 11.34, "cov_scale": 1.0}
    assert resolved_config("isam2", {"kinds": {"cairns": {"gate_m": 0.5}}})["kinds"]["cairns"]["gate_m"] == 0.5
    inputs, _ = world
    ekf = make_backend("ekf", inputs.initial, {"kinds": {"cairns": {"gate_chi2": 5.0}}})
    cairn = next(m for m in inputs.measurements if isinstance(m, CairnObservations) and len(m))
    ekf.observe(cairn)
    assert ekf._kinds.named("cairns").cfg.gate_chi2 == 5.0
    with pytest.raises(ConfigError, match="no_such"):
        make_backend("ekf", inputs.initial, {"kinds": {"cairns": {"no_such": 1}}}).observe(cairn)
    with pytest.raises(EkfInputError, match="'lava_tubes'"):
        make_backend("ekf", inputs.initial, {"kinds": {"lava_tubes": {}}})
    with pytest.raises(SmootherError, match="'lava_tubes'"):
        make_backend("isam2", inputs.initial, {"kinds": {"lava_tubes": {}}})


def test_a_sim_directory_with_a_cairn_catalog_compares_and_records(tmp_path, cairns):
    from rerun.chunk import RrdReader

    from fgslam.compare import CompareConfig, compare_world
    from fgslam.inputs import load_sim_dir
    from fgslam.io.catalog_csv import write_catalog_csv
    from fgslam.viz import rerun_log
    from sim.bag_writer import write_bag

    inputs, _ = _with_cairns(make_stream(seed=11, duration_s=30.0), seed=1)  # a short traverse: 4 passes
    write_bag(tmp_path / "d" / "bag", inputs.measurements)
    write_catalog_csv(tmp_path / "d" / "catalog.csv", inputs.catalogs["rocks"])
    write_cairn_csv(tmp_path / "d" / "cairns.csv", inputs.catalogs["cairns"])
    loaded = load_sim_dir(tmp_path / "d")
    assert set(loaded.catalogs) == {"rocks", "cairns"} and len(loaded.catalogs["cairns"]) == 40
    cfg = CompareConfig(backends=("ekf",), reference_backend="ekf", workers=1,
                        kind_relocalizers={"cairns": {"period_s": 4.0}})
    rocks = Relocalizer(loaded.catalogs["rocks"], cfg.relocalizer, matcher=NearestNeighbourMatcher(loaded.catalogs["rocks"].xy_m))
    wc = compare_world(loaded, cfg, relocalizers=[rocks, CairnRelocalizer(loaded.catalogs["cairns"], {"period_s": 4.0})])
    assert wc.metrics["runs"]["ekf_reloc"]["landmarks_by_kind"]["cairns"] >= 5
    assert {a.source for a in wc.attempts} == {"rocks", "cairns"}
    path = rerun_log.write_comparison_rrd(tmp_path / "c.rrd", [wc])
    paths = {c.entity_path for c in RrdReader(path).stream()}
    w = "/" + loaded.name
    assert {f"{w}/map/catalog/cairns", f"{w}/map/catalog/rocks", f"{w}/ekf_reloc/landmarks/cairns",
            f"{w}/ekf_reloc/landmarks/rocks"} <= paths

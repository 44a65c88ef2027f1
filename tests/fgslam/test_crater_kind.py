"""The crater kind end to end on a seeded synthetic traverse (tests/fgslam/_synth_stream.py with
its crater field): the /craters bag topic, both back-ends' crater maps, the EKF's replay and the
smoother's fixed lag, the crater relocalizer's fixes, craters alone bounding the drift, its
settings, and the crater catalog file."""

from __future__ import annotations

import numpy as np
import pytest
from _synth_stream import make_stream

from fgslam.backends.registry import make_backend
from fgslam.fix_sources import OnlineFixes, relocalizers_for
from fgslam.inputs import truth_of
from fgslam.metrics import ate, fix_errors
from fgslam.runner import run_backend
from reloc.craters import CraterObservations
from reloc.kinds import kind_named
from reloc.measurements import RockObservations


@pytest.fixture(scope="module")
def synth():
    return make_stream(seed=5, duration_s=60.0, craters=True)


def _map_error(lmap, true_xy) -> np.ndarray:
    d = np.linalg.norm(lmap.xyz_world_m[:, None, :2] - true_xy[None], axis=2)
    return d.min(axis=1)


def test_the_kind_is_registered_with_every_layer():
    k = kind_named("craters")
    assert k.symbol == "r" and k.rank == 5 and k.measurement_type is CraterObservations
    for layer in ("bag", "ekf", "smoother", "relocalizer", "catalog", "rerun"):
        assert k.layer(layer) is not None


def test_craters_travel_through_a_bag(tmp_path, synth):
    from rosbags.highlevel import AnyReader

    from fgslam.io.bag_reader import read_bag
    from sim.bag_writer import write_bag

    write_bag(tmp_path / "bag", synth.measurements)
    stream = read_bag(tmp_path / "bag")
    want = [m for m in synth.measurements if isinstance(m, CraterObservations)]
    got = stream.of_type(CraterObservations)
    assert len(got) == len(want) > 10 and stream.report.topics["/craters"].role == "craters"
    for a, b in zip(got, want):
        assert a.t == pytest.approx(b.t, abs=1e-9)
        for f in ("xyz_base_m", "cov_base_m2", "size_m", "size_sigma_m", "completeness", "score"):
            np.testing.assert_allclose(getattr(a, f), getattr(b, f), err_msg=f)
    assert len(stream.of_type(RockObservations)) == sum(isinstance(m, RockObservations) for m in synth.measurements)
    with AnyReader([tmp_path / "bag"]) as reader:
        assert reader.topics["/craters"].msgtype == "vision_msgs/msg/Detection3DArray"


def test_the_decoder_defaults_a_crater_without_its_rim_hypothesis_and_refuses_bad_ones():
    from types import SimpleNamespace as NS

    from reloc.bag_spec import DecodeContext, MessageContentError, UnknownFrameError, typestore
    from reloc.crater_bag import DEFAULT_DIAMETER_SIGMA_REL, CraterDecoder
    from reloc.detections import Detections, parse_detection3d_array

    ts = typestore()
    T = ts.types

    def header(frame):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=frame)

    def pose(x=0.0, y=0.0):
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))

    def hyp(class_id, score, cov):
        return T["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=class_id, score=score),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(), covariance=np.asarray(cov, float)))

    def frame(cov, det_frame="base_link", rim=None):
        det = T["vision_msgs/msg/Detection3D"](
            header=header(det_frame), results=[hyp("crater", 0.7, cov)] + ([rim] if rim is not None else []),
            bbox=T["vision_msgs/msg/BoundingBox3D"](center=pose(9.0, 1.0),
                                                    size=T["geometry_msgs/msg/Vector3"](x=4.0, y=4.0, z=0.0)),
            id="")
        return T["vision_msgs/msg/Detection3DArray"](header=header("base_link"), detections=[det])

    def forms(msg):  # as rosbags deserializes it, and as reloc.detections parses its bytes
        raw = bytes(ts.serialize_cdr(msg, "vision_msgs/msg/Detection3DArray"))
        return msg, parse_detection3d_array(raw)

    ctx = DecodeContext(NS(base_frame="base_link"), {"base_link": np.eye(4)})
    good = (np.eye(6) * 0.04).ravel()
    dec = CraterDecoder(ctx)
    for msg in forms(frame(good)):
        o = dec(msg, 2_000_000_000)
        assert o.t == 2.0 and o.completeness[0] == 1.0
        assert o.size_sigma_m[0] == pytest.approx(4.0 * DEFAULT_DIAMETER_SIGMA_REL)
    rim = np.zeros(36)
    rim[0] = 0.09
    for msg in forms(frame(good, rim=hyp("crater_rim", 0.5, rim))):
        o = dec(msg, 0)
        assert o.completeness[0] == 0.5 and o.size_sigma_m[0] == pytest.approx(0.3)
    bad = ((MessageContentError, "positive-definite", frame(np.zeros(36))),
           (MessageContentError, "diameter variance", frame(good, rim=hyp("crater_rim", 0.5, np.zeros(36)))),
           (UnknownFrameError, "'mast'", frame(good, det_frame="mast")))
    for error, match, m in bad:
        for msg in forms(m):
            assert isinstance(msg, (Detections, type(m)))
            with pytest.raises(error, match=match):
                dec(msg, 0)


@pytest.mark.parametrize("name,tol_m", [("ekf", 0.6), ("isam2", 0.6), ("dr", 1.5)])
def test_every_backend_maps_the_craters_beside_the_rocks(synth, name, tol_m):
    from _synth_stream import CraterField

    field = CraterField.draw(5, 3 * 40.0)
    be = make_backend(name, synth.initial)
    res = run_backend(be, synth.measurements)
    lm = res.landmarks["craters"]
    assert len(lm) >= 8 and len(res.landmarks["rocks"]) > 20
    assert np.median(_map_error(lm, field.xy)) < tol_m


def test_craters_left_out_by_setting_map_nothing(synth):
    for name in ("ekf", "isam2"):
        be = make_backend(name, synth.initial, {"kinds": {"craters": {"use": False}}})
        res = run_backend(be, synth.measurements)
        assert len(res.landmarks["craters"]) == 0 and len(res.landmarks["rocks"]) > 20


def test_the_ekf_replays_crater_frames_after_a_late_fix(synth):
    from fgslam.fix_sources import ReplayedFixes
    from reloc.measurements import GlobalFix

    gt = truth_of(synth)
    fixes = []
    for t in (20.0, 40.0):
        T = gt.T_world_base[np.searchsorted(gt.t, t)]
        fixes.append(GlobalFix(t, t + 6.0, T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])), np.eye(3) * 1e-3))
    ekf = make_backend("ekf", synth.initial, {"kinds": {"craters": {"period_s": 0.0}}})
    res = run_backend(ekf, synth.measurements, ReplayedFixes(fixes))
    extra = ekf.stats().extra
    assert all(o.accepted for o in res.outcomes) and extra["n_replayed_entries"] > 0
    n_det = sum(len(m) for m in synth.measurements if isinstance(m, CraterObservations))
    # counted once per detection however often replayed (each is associated, new, or left out)
    used = extra["crater_n_associated"] + extra["crater_n_initialised"]
    assert 0.5 * n_det < used <= n_det


def test_the_fixed_lag_smoother_marginalizes_craters(synth):
    sm = make_backend("isam2", synth.initial, {"fixed_lag_s": 10.0})
    res = run_backend(sm, synth.measurements)
    layer = sm.kinds.get("craters")
    assert len(res.landmarks["craters"]) >= 8 and len(layer.store._retired) > 0
    assert len(layer.store.live) < len(res.landmarks["craters"])  # retired ones stay in the map


def test_crater_fixes_are_right_and_bound_the_drift_where_craters_alone_are_seen():
    """Rocks left out of the stream: a slipping rover with a gyro bias drifts; the crater
    relocalizer on the crater catalog alone keeps iSAM2 and the EKF near the truth, seeded."""
    synth = make_stream(seed=8, duration_s=150.0, slip=0.9, gyro_bias_radps=0.001, craters=True, rocks_on=False)
    gt = truth_of(synth)
    cat = {"craters": synth.catalogs["craters"]}
    drift = ate(run_backend(make_backend("dr", synth.initial), synth.measurements).final, gt)
    for name in ("isam2", "ekf"):
        res = run_backend(make_backend(name, synth.initial), synth.measurements, OnlineFixes(relocalizers_for(cat)))
        fixes = [a.fix for a in res.attempts if a.fix is not None]
        assert len(fixes) >= 10 and all(a.source == "craters" for a in res.attempts)
        assert all(o.accepted for o in res.outcomes)
        err, _ = fix_errors(np.array([f.xyyaw for f in fixes]), np.array([f.t_meas for f in fixes]), gt)
        assert err.max() < 0.5, err
        got = ate(res.final, gt)  # dead reckoning: 2.4 m RMSE
        assert got.rmse < 0.15 * drift.rmse and got.max < 0.6, (name, got.rmse, drift.rmse)


def test_crater_relocalizer_settings_merge_over_the_crater_defaults():
    from fgslam.crater_relocalizer import CRATER_RELOCALIZER_DEFAULTS, crater_relocalizer_config
    from reloc.config import ConfigError

    cfg = crater_relocalizer_config({"period_s": 4.0, "matcher": {"sigma_m": 0.5}})
    assert cfg.period_s == 4.0 and cfg.max_radius_m == CRATER_RELOCALIZER_DEFAULTS.max_radius_m
    assert cfg.matcher["sigma_m"] == 0.5 and cfg.matcher["size_ratio_max"] == 1.5
    assert crater_relocalizer_config(None) == CRATER_RELOCALIZER_DEFAULTS
    with pytest.raises(ConfigError, match="no_such"):
        crater_relocalizer_config({"no_such": 1})


def test_the_crater_catalog_file_is_read_and_checked(tmp_path):
    from fgslam.errors import InputFileError
    from fgslam.io.crater_csv import CRATER_CATALOG_FILE

    f = tmp_path / "craters.csv"
    f.write_text("x,y,size,score\n1,2,4.5,0.9\n10,2,3.0,0.8\n5,9,12.0,0.7\n")
    cat = CRATER_CATALOG_FILE.read(f)
    assert CRATER_CATALOG_FILE.file_name == "craters.csv" and len(cat) == 3 and cat.size_m[2] == 12.0
    f.write_text("x,y,size,score\n1,2,4.5,0.9\n")
    with pytest.raises(InputFileError, match="holds 1 craters"):
        CRATER_CATALOG_FILE.read(f)
    f.write_text("x,y,size\n1,2,-4\n")
    with pytest.raises(InputFileError, match="positive diameter"):
        CRATER_CATALOG_FILE.read(f)


def test_a_sim_directory_with_craters_compares_and_draws_rims(tmp_path):
    from rerun.chunk import RrdReader

    from fgslam.compare import CompareConfig, compare_world
    from fgslam.inputs import load_sim_dir
    from fgslam.io.catalog_csv import write_catalog_csv
    from fgslam.viz import rerun_log
    from sim.bag_writer import write_bag

    synth = make_stream(seed=11, duration_s=40.0, craters=True)
    write_bag(tmp_path / "d" / "bag", synth.measurements)
    write_catalog_csv(tmp_path / "d" / "catalog.csv", synth.catalogs["rocks"])
    write_catalog_csv(tmp_path / "d" / "craters.csv", synth.catalogs["craters"])
    loaded = load_sim_dir(tmp_path / "d")
    assert set(loaded.catalogs) == {"rocks", "craters"}
    cfg = CompareConfig(backends=("ekf",), reference_backend="ekf", workers=1, kind_relocalizers={"craters": {"period_s": 5.0}})
    wc = compare_world(loaded, cfg)
    assert wc.metrics["runs"]["ekf_reloc"]["landmarks_by_kind"]["craters"] >= 5
    assert "craters" in {a.source for a in wc.attempts}
    assert any(a.fix is not None for a in wc.attempts if a.source == "craters")
    path = rerun_log.write_comparison_rrd(tmp_path / "c.rrd", [wc])
    paths = {c.entity_path for c in RrdReader(path).stream()}
    w = "/" + loaded.name
    assert {f"{w}/map/catalog/craters", f"{w}/ekf_reloc/landmarks/craters", f"{w}/ekf_reloc/landmarks/craters/rims"} <= paths


def _cli(args, capsys) -> tuple[int, str, str]:
    from fgslam.cli import main

    try:
        rc = main(args)
    except SystemExit as exc:
        rc = exc.code
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_bench_craters_measures_a_directory_and_refuses_bad_arguments(tmp_path, capsys):
    import json

    from fgslam.io.catalog_csv import write_catalog_csv
    from sim.bag_writer import write_bag

    synth = make_stream(seed=8, duration_s=60.0, gyro_bias_radps=0.001, craters=True)
    d = tmp_path / "d"
    write_bag(d / "bag", synth.measurements)
    write_catalog_csv(d / "catalog.csv", synth.catalogs["rocks"])
    rc, _, err = _cli(["bench", "craters", str(d), "--passes", "craters alone"], capsys)
    assert rc == 2 and "no craters.csv" in err
    write_catalog_csv(d / "craters.csv", synth.catalogs["craters"])
    for args, msg in ((["--passes", "all of them"], "unknown pass"), (["--backend", "dr"], "--backend must be"),
                      (["--duration-s", "0"], "--duration-s must be > 0")):
        rc, _, err = _cli(["bench", "craters", str(d), *args], capsys)
        assert rc == 2 and msg in err, err
    rc, out, _ = _cli(["bench", "craters", str(d), "--passes", "craters alone,no fixes", "--duration-s", "50",
                       "--out", str(tmp_path / "o")], capsys)
    assert rc in (0, None) and "craters alone" in out
    res = json.loads((tmp_path / "o" / "results.json").read_text())["results"][0]["passes"]
    cr = res["craters alone"]["crater_reloc"]
    assert cr["attempts"] >= 3 and cr["with_min_catalogued"] >= 2 and cr["succeeded"] == cr["with_min_catalogued"]
    assert res["craters alone"]["fixes"]["craters"]["wrong"] == 0
    assert res["craters alone"]["ate_rmse_m"] < res["no fixes"]["ate_rmse_m"] + 0.05


def test_bench_craters_runs_each_pass_as_fgslam_run_does_with_the_directory_config(tmp_path):
    """The bench's passes take the directory's backend.yaml whole (relocalizer settings included):
    its rocks + craters pass is `fgslam run DIR` to the digit, and a setting there changes it."""
    import fgslam
    from fgslam.bench.craters import CraterBenchConfig, bench_directory
    from fgslam.io.catalog_csv import write_catalog_csv
    from sim.bag_writer import write_bag

    synth = make_stream(seed=8, duration_s=60.0, gyro_bias_radps=0.001, craters=True)
    d = tmp_path / "d"
    write_bag(d / "bag", synth.measurements)
    write_catalog_csv(d / "catalog.csv", synth.catalogs["rocks"])
    write_catalog_csv(d / "craters.csv", synth.catalogs["craters"])
    plain = fgslam.run(d, backend="ekf")
    (d / "backend.yaml").write_text("kind_relocalizers:\n  craters: {inflation: 5.0, delay_s: 5.0}\n"
                                    "relocalizer: {inflation: 5.0}\n")
    run = fgslam.run(d, backend="ekf")
    bench = bench_directory(d, CraterBenchConfig(backend="ekf", passes=("rocks + craters",)))["passes"]["rocks + craters"]
    ate_run = run.metrics["ate"]["rmse"]
    assert abs(ate_run - plain.metrics["ate"]["rmse"]) > 1e-4  # the settings are felt
    assert bench["ate_rmse_m"] == pytest.approx(ate_run, rel=1e-9)
    for source in ("rocks", "craters"):
        made = [a for a in run.result.attempts if a.source == source]
        assert bench["fixes"][source]["attempts"] == len(made)
        assert bench["fixes"][source]["fixes"] == sum(1 for a in made if a.fix is not None)
        assert sum(bench["fixes"][source]["statuses"].values()) == len(made)

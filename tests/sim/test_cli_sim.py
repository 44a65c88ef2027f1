"""``fgslam sim`` smoke test on a short traverse: every output file, read back independently."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import yaml

from fgslam.cli import main


def test_fgslam_sim_writes_bag_catalog_world_and_image(tmp_path, capsys):
    out = tmp_path / "run"
    cfg = tmp_path / "sim.yaml"
    cfg.write_text("sensors:\n  stereo:\n    rate_hz: 1.0\n  orbital:\n    preset: ideal\n")
    rc = main(["sim", "--world", "my2022", "--seed", "1", "--out", str(out), "--distance-m", "6", "--config", str(cfg)])
    assert rc == 0
    for name in ("bag/metadata.yaml", "catalog.csv", "rocks_true.csv", "world.yaml", "orbital.png"):
        assert (out / name).is_file(), name
    assert list((out / "bag").glob("*.mcap"))
    with open(out / "catalog.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["x", "y", "size", "score"] and len(rows) > 50
    world = yaml.safe_load((out / "world.yaml").read_text())
    assert world["world"] == "my2022" and world["seed"] == 1
    assert world["extent"] == [-25.0, 25.0, -25.0, 25.0]
    assert world["config"]["sensors"]["stereo"]["rate_hz"] == 1.0
    assert world["config"]["sensors"]["orbital"]["recall"] == 1.0  # the ideal preset, resolved
    assert world["config"]["traverse"]["distance_m"] == 6.0
    rocks = np.genfromtxt(out / "rocks_true.csv", delimiter=",", names=True)
    assert len(rocks) == 294 and {"x", "y", "size"} <= set(rocks.dtype.names)

    import cv2

    img = cv2.imread(str(out / "orbital.png"))
    assert img.shape == (1000, 1000, 3)

    from fgslam.io import read_bag
    from reloc.measurements import RockObservations

    stream = read_bag(out / "bag")
    meas = list(stream.measurements)
    frames = [m for m in meas if isinstance(m, RockObservations)]
    duration = world["stats"]["duration_s"]
    assert len(frames) == int(duration) + 1  # 1 Hz from the YAML override
    assert "drift" in capsys.readouterr().out


def test_fgslam_sim_rejects_an_unknown_config_key(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("sensors:\n  stereo:\n    fov_deg: 90\n")
    rc = main(["sim", "--world", "my2022", "--out", str(tmp_path / "x"), "--config", str(cfg)])
    assert rc == 2
    assert "fov_deg" in capsys.readouterr().err


def test_write_outputs_catalog_reads_back_with_the_fgslam_reader(tmp_path):
    from _sim_runs import short_run

    from fgslam.io.catalog_csv import read_catalog_csv
    from sim.outputs import write_outputs

    run = short_run()
    paths = write_outputs(run, tmp_path, orbital_gsd_m=0.2)
    cat = read_catalog_csv(paths["catalog.csv"])
    np.testing.assert_allclose(cat.xy_m, run.catalog.xy_m, atol=1e-4)
    np.testing.assert_allclose(cat.size_m, run.catalog.size_m, atol=1e-4)
    world = yaml.safe_load(paths["world.yaml"].read_text())
    assert world["stats"]["n_catalog"] == len(cat)
    assert world["orbital_gsd_m"] == 0.2


def test_cli_sim_image_detections_path(tmp_path):
    """--detections image: /rocks and the catalog come from rendering + the shipped ONNX detectors."""
    from fgslam.cli import main
    from fgslam.io.bag_reader import read_bag
    from fgslam.io.catalog_csv import read_catalog_csv
    from reloc.measurements import RockObservations

    out = tmp_path / "img"
    rc = main(["sim", "--world", "cnes", "--seed", "0", "--distance-m", "3",
               "--detections", "image", "--image-rate-hz", "0.5", "--out", str(out)])
    assert rc == 0
    frames = read_bag(out / "bag").of_type(RockObservations)
    assert len(frames) >= 5 and sum(len(f) for f in frames) > 0
    assert len(read_catalog_csv(out / "catalog.csv")) > 10
    assert main(["sim", "--world", "cnes", "--distance-m", "3", "--detections", "pixels",
                 "--out", str(tmp_path / "bad")]) != 0


def test_a_kilometre_run_sizes_the_matcher_to_its_catalog_and_its_world_yaml_is_accepted_back(tmp_path):
    """backend.yaml carries the rock matcher's sigma of this catalog (2 px at 0.25 m/px), the
    catalog's true entries scatter by that much, and world.yaml (with the kilometre preset's
    extra records) is accepted back by --config as the same simulator config."""
    from fgslam.cli.cmd_sim import load_sim_config
    from fgslam.config_file import load_compare_config
    from reloc.config import config_to_dict

    out = tmp_path / "km"
    assert main(["sim", "--world", "rocky-1km", "--seed", "3", "--out", str(out), "--distance-m", "5"]) == 0
    cfg = load_compare_config(out / "backend.yaml")
    sigma = cfg.relocalizer.matcher["sigma_m"]
    assert sigma == 0.5
    from sim.tiled.presets import TACTICAL_GYRO  # the preset's IMU, as a datasheet tells the EKF
    ekf = cfg.backend_overrides["ekf"]
    assert ekf["yaw_rate_bias_sigma_radps"] == TACTICAL_GYRO["gyro_bias_sigma_radps"]
    assert ekf["yaw_rate_bias_walk_radps_rsqrt_s"] == TACTICAL_GYRO["gyro_bias_walk_radps_rsqrt_s"]
    # the smoother: the gyro's angle random walk and its bias as white over 300 s; the mounting's
    # roll and pitch and the range scale as its calibration variable (not the mounting's yaw)
    isam2 = cfg.backend_overrides["isam2"]
    rot = isam2["odometry"]["sigma_rot_radpsqrts"]
    assert rot == pytest.approx(np.hypot(4.4e-5, TACTICAL_GYRO["gyro_bias_sigma_radps"] * np.sqrt(300.0)), rel=1e-3)
    assert isam2["calibration"] == {"roll_pitch_sigma_deg": 0.15, "scale_sigma": 0.003}
    cat = np.genfromtxt(out / "catalog.csv", delimiter=",", names=True)
    rid = np.loadtxt(out / "catalog_truth.csv", skiprows=1, dtype=np.int64)
    rocks = np.genfromtxt(out / "rocks_true.csv", delimiter=",", names=True, dtype=None)
    where = {int(i): k for k, i in enumerate(rocks["id"])}
    true = np.flatnonzero(rid >= 0)
    assert len(true) > 30
    k = np.array([where[int(i)] for i in rid[true]])
    err = np.concatenate([cat["x"][true] - rocks["x"][k], cat["y"][true] - rocks["y"][k]])
    assert 0.8 * sigma < np.std(err) < 1.2 * sigma  # the matcher's sigma is the catalog's real scatter
    world = yaml.safe_load((out / "world.yaml").read_text())
    assert world["relocalizer"] == {"matcher": {"sigma_m": 0.5}}
    assert config_to_dict(load_sim_config(None, None, None, out / "world.yaml")) == world["config"]


def test_a_kilometre_bag_in_the_robot_style_carries_tf_and_real_stamps_and_runs(tmp_path):
    """--bag-style robot on a kilometre world: the robot's topic names, 2026 stamps, /tf_static
    (world -> odom at the start, base_link -> the mast camera), /tf with every ground-truth pose,
    the catalog named in the metadata; `fgslam run` takes it with the robot's topic map."""
    from rosbags.highlevel import AnyReader

    from sim.bag_scene import ROBOT_EPOCH_NS, ROBOT_TOPICS

    out = tmp_path / "km"
    assert main(["sim", "--world", "rocky-1km", "--seed", "2", "--distance-m", "4", "--bag-style", "robot",
                 "--out", str(out)]) == 0
    meta = yaml.safe_load((out / "bag" / "metadata.yaml").read_text())
    assert meta["rosbag2_bagfile_information"]["custom_data"]["fgslam.catalog"] == "catalog.csv"
    bag = yaml.safe_load((out / "world.yaml").read_text())["bag"]  # how it was written
    assert bag["topics"]["imu"] == ROBOT_TOPICS.imu and bag["epoch_ns"] == ROBOT_EPOCH_NS and not bag["images"]
    with AnyReader([out / "bag"]) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert {ROBOT_TOPICS.imu, ROBOT_TOPICS.wheel_odom, "/tf", "/tf_static"} <= set(topics)
        assert reader.start_time >= ROBOT_EPOCH_NS
        static = [reader.deserialize(raw, c.msgtype)
                  for c, _, raw in reader.messages(connections=[topics["/tf_static"]])]
        pairs = {(t.header.frame_id, t.child_frame_id) for m in static for t in m.transforms}
        assert ("world", "odom") in pairs and any(p == "base_link" for p, _ in pairs)
        n_tf = sum(1 for _ in reader.messages(connections=[topics["/tf"]]))
        n_truth = sum(1 for _ in reader.messages(connections=[topics[ROBOT_TOPICS.ground_truth]]))
        assert n_tf == n_truth > 0
    assert main(["run", str(out), "--backend", "ekf", "--no-reloc", "--topic", f"imu={ROBOT_TOPICS.imu}",
                 "--topic", f"wheel_odom={ROBOT_TOPICS.wheel_odom}", "--out", str(tmp_path / "run")]) == 0
    assert (tmp_path / "run" / "ekf.tum").is_file()

"""Images in (issue 16): a simulated image bag recorded like a rover's (compressed stereo images,
CameraInfo, /tf_static, an unstamped Twist, /imu/data, /odom, 2026 stamps, no rock topic) goes
through `fgslam detect` (resumable) and `fgslam run` (on the fly) with a topic map; the rocks read
back from the images equal the simulator's own detections of the same rendered pairs; an
independent reader (mcap-ros2) resolves /tf and puts the rocks where the true rocks are."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from fgslam.cli import main
from fgslam.io import read_bag
from fgslam.io.detect_bag import DetectCheckpoint
from fgslam.io.sim_dir import sim_output_dir, write_sim_files
from reloc.bag_spec import TopicNames
from reloc.camera_bag import StereoFrame
from reloc.measurements import RockObservations
from sim.bag_scene import ROBOT_EPOCH_NS, bag_style
from sim.config import SimConfig, TraverseConfig
from sim.image_detections import ImageDetectionConfig, with_image_detections
from sim.simulate import simulate

ROBOT_ARGS = ["--topic", "imu=/imu/data", "--topic", "wheel_odom=/odom"]


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    """One rendered traverse written twice: fgslam's style (its /rocks beside the images) and a
    rover's (the images only)."""
    cfg = SimConfig(world="cnes", seed=0, traverse=TraverseConfig(distance_m=2.5))
    frames: list = []
    run = with_image_detections(simulate(cfg), ImageDetectionConfig(rate_hz=0.5),
                                on_frame=lambda t, sr: frames.append(StereoFrame(t, sr.left, sr.right)))
    root = tmp_path_factory.mktemp("img")
    for name, rock_topic in (("fgslam", True), ("robot", False)):
        style, topics = bag_style(name)
        with sim_output_dir(root / name) as od:
            write_sim_files(run, od.staging, style, topics, frames, rock_topic=rock_topic)
            od.commit()
    return root, run


def _rocks(bag: Path, topic: str) -> list[RockObservations]:
    stream = read_bag(bag, TopicNames(rocks=topic, imu="/imu/data", wheel_odom="/odom", cmd_vel="/cmd_vel"), kinds=["rocks"])
    return stream.of_type(RockObservations)


def test_detect_gives_the_simulators_detections_back(dirs, tmp_path):
    root, _ = dirs
    out = tmp_path / "detected"
    assert main(["detect", str(root / "fgslam" / "bag"), "--out", str(out), "--topic", "rocks=/rocks_from_images"]) == 0
    own = read_bag(out).of_type(RockObservations)  # the simulator's /rocks, copied unchanged
    ts = TopicNames(rocks="/rocks_from_images")
    back = read_bag(out, ts, kinds=["rocks"]).of_type(RockObservations)
    assert len(back) == len(own) >= 5 and sum(len(o) for o in back) > 10
    for a, b in zip(own, back):
        assert a.t == pytest.approx(b.t, abs=1e-9)
        np.testing.assert_allclose(b.xyz_base_m, a.xyz_base_m, atol=1e-9)
        np.testing.assert_allclose(b.cov_base_m2, a.cov_base_m2, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(b.size_m, a.size_m, atol=1e-9)


def test_a_rover_style_bag_runs_by_detect_and_on_the_fly_alike(dirs, tmp_path, capsys):
    root, _ = dirs
    bag = root / "robot" / "bag"
    assert main(["detect", str(bag), "--out", str(tmp_path / "det")]) == 0
    assert "frames/s" in capsys.readouterr().err
    rocks = _rocks(tmp_path / "det", "/rocks")
    assert rocks and min(r.t for r in rocks) >= ROBOT_EPOCH_NS / 1e9
    base = ["run", "--backend", "ekf", "--catalog", str(root / "robot" / "catalog.csv"), *ROBOT_ARGS]
    assert main([*base, "--bag", str(tmp_path / "det"), "--out", str(tmp_path / "r_det")]) == 0
    assert main([*base, "--bag", str(bag), "--out", str(tmp_path / "r_fly")]) == 0
    a, b = ((tmp_path / d / "ekf_reloc.tum").read_text() for d in ("r_det", "r_fly"))
    assert a == b
    met = json.loads((tmp_path / "r_fly" / "metrics.json").read_text())
    assert met["ate"]["rmse"] < 0.5
    # the simulator's directory runs too: the same images, the same rocks
    assert main(["run", str(root / "robot"), "--backend", "ekf", *ROBOT_ARGS, "--out", str(tmp_path / "r_dir")]) == 0
    assert (tmp_path / "r_dir" / "ekf_reloc.tum").read_text() == a


def test_detect_resumes_from_its_saved_frames(dirs, tmp_path, capsys):
    root, _ = dirs
    bag, out = root / "robot" / "bag", tmp_path / "det"
    assert main(["detect", str(bag), "--out", str(tmp_path / "full")]) == 0
    full = _rocks(tmp_path / "full", "/rocks")
    # a stopped run saved its first three frames (marked: their scores are halved)
    from fgslam.cli.cmd_run import load_config
    from fgslam.inputs import bag_topics
    from reloc.config import config_to_dict

    settings = {"images": config_to_dict(load_config(None).images), "topics": bag_topics().as_roles()}
    cp = DetectCheckpoint(out, bag, settings)
    for m in full[:3]:
        cp.add(round(m.t * 1e9), RockObservations(m.t, m.xyz_base_m, m.cov_base_m2, m.size_m, 0.5 * m.score))
    cp.flush()
    assert main(["detect", str(bag), "--out", str(out)]) == 0
    resumed = _rocks(out, "/rocks")
    assert len(resumed) == len(full)
    for k, (a, b) in enumerate(zip(full, resumed)):
        np.testing.assert_allclose(b.score, a.score * (0.5 if k < 3 else 1.0))
    assert not cp.dir.exists()
    # a work directory of other settings is refused, naming it
    cp2 = DetectCheckpoint(tmp_path / "other", bag, {"x": 1})
    cp2.flush()
    assert main(["detect", str(bag), "--out", str(tmp_path / "other")]) == 2
    assert "--restart" in capsys.readouterr().err
    assert main(["detect", str(bag), "--out", str(tmp_path / "other"), "--restart"]) == 0


def test_missing_image_topics_are_named_with_the_bags_topics(dirs, tmp_path, capsys):
    root, _ = dirs
    assert main(["detect", str(root / "robot" / "bag"), "--out", str(tmp_path / "x"),
                 "--topic", "left_image=/cam/left"]) == 2
    err = capsys.readouterr().err
    assert "/cam/left" in err and "/stereo/left/image_raw/compressed (sensor_msgs/msg/CompressedImage" in err
    assert main(["detect", str(root / "robot" / "bag"), "--out", str(tmp_path / "x")]) == 0
    assert main(["detect", str(root / "robot" / "bag"), "--out", str(tmp_path / "x")]) == 2  # exists
    assert "--overwrite" in capsys.readouterr().err


def test_an_independent_reader_resolves_tf_and_puts_rocks_on_true_rocks(dirs):
    """mcap-ros2 (not rosbags) decodes /tf, /tf_static and /rocks; each detected rock, moved
    world <- base_link by the /tf of its stamp, lies on a true rock of the world."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from scipy.spatial.transform import Rotation

    root, run = dirs
    path = next((root / "fgslam" / "bag").glob("*.mcap"))
    tf: dict[int, np.ndarray] = {}
    static, rocks = {}, []
    with open(path, "rb") as fh:
        for _, channel, message, msg in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/tf", "/tf_static", "/rocks"]):
            if channel.topic == "/rocks":
                rocks.append(msg)
                continue
            for t in msg.transforms:
                q, p = t.transform.rotation, t.transform.translation
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                T[:3, 3] = [p.x, p.y, p.z]
                key = (t.header.frame_id, t.child_frame_id)
                if channel.topic == "/tf_static":
                    static[key] = T
                else:
                    assert key == ("world", "base_link")
                    tf[t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec] = T
    assert {("world", "odom"), ("base_link", "stereo_left_optical")} <= set(static)
    np.testing.assert_allclose(static[("world", "odom")], run.ground_truth.T_world_base[0], atol=1e-9)
    stamps = np.array(sorted(tf))
    true_xy = run.world.rocks.xyz_m[:, :2]
    errors = []
    for msg in rocks:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        T = tf[int(stamps[np.argmin(np.abs(stamps - ns))])]
        for det in msg.detections:
            c = det.bbox.center.position
            xyz_world = T[:3, :3] @ [c.x, c.y, c.z] + T[:3, 3]
            errors.append(np.min(np.linalg.norm(true_xy - xyz_world[:2], axis=1)))
    assert len(errors) > 10
    assert np.median(errors) < 0.15  # stereo at a few metres: centimetres to a decimetre


def test_world_yaml_records_how_the_bag_was_written(dirs):
    """world.yaml says the bag's style, whether it holds images and its topic names (the --topic
    map a run of the robot-style bag needs), and the bag has those topics."""
    from rosbags.highlevel import AnyReader

    from sim.bag_scene import ROBOT_EPOCH_NS

    root, _ = dirs
    for name, imu, epoch in (("fgslam", "/imu", 0), ("robot", "/imu/data", ROBOT_EPOCH_NS)):
        bag = yaml.safe_load((root / name / "world.yaml").read_text())["bag"]
        assert bag["epoch_ns"] == epoch and bag["images"] and bag["image_format"] == "png" and bag["tf"]
        assert bag["topics"]["imu"] == imu and bag["cmd_vel_stamped"] == (name == "fgslam")
        with AnyReader([root / name / "bag"]) as reader:
            assert {bag["topics"]["imu"], bag["topics"]["left_info"]} <= set(reader.topics)
            assert any(t.startswith(bag["topics"]["left_image"]) for t in reader.topics)

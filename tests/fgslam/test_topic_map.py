"""Topic mapping (issue 16): a bag recorded under a real robot's names (/imu/data, /odom, an
unstamped Twist on /cmd_vel_raw) runs with --topic ROLE=NAME or a topics: block, gives the same
result as under fgslam's own names, and a missing topic is an error listing the bag's topics."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from _synth_stream import make_stream

from fgslam.cli import main
from fgslam.inputs import bag_topics
from fgslam.io.catalog_csv import write_catalog_csv
from reloc.bag_spec import TopicNames, parse_topic_options
from reloc.errors import ConfigError
from sim.bag_scene import BagStyle
from sim.bag_writer import write_bag

ROBOT = {"imu": "/imu/data", "cmd_vel": "/cmd_vel_raw", "wheel_odom": "/odom", "rocks": "/stereo/rocks",
         "ground_truth": "/gt/odom"}
ROBOT_ARGS = [a for role, name in ROBOT.items() for a in ("--topic", f"{role}={name}")]


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    s = make_stream(seed=3, duration_s=20.0)
    root = tmp_path_factory.mktemp("topics")
    for name, topics, style in (("own", TopicNames(), BagStyle()),
                                ("robot", TopicNames(**ROBOT), BagStyle(cmd_vel_stamped=False))):
        (root / name).mkdir()
        write_bag(root / name / "bag", s.measurements, topics=topics, style=style)
        write_catalog_csv(root / name / "catalog.csv", s.catalog)
    return root


def _ate(out: Path) -> float:
    return json.loads((out / "metrics.json").read_text())["ate"]["rmse"]


def test_a_robots_names_map_by_option_and_by_config_block(dirs, tmp_path):
    base = ["run", "--backend", "ekf", "--no-reloc"]
    assert main([*base, str(dirs / "own"), "--out", str(tmp_path / "own")]) == 0
    assert main([*base, str(dirs / "robot"), "--out", str(tmp_path / "opt"), *ROBOT_ARGS]) == 0
    (tmp_path / "t.yaml").write_text(yaml.safe_dump({"topics": ROBOT}))
    assert main([*base, "--bag", str(dirs / "robot" / "bag"), "--catalog", str(dirs / "robot" / "catalog.csv"),
                 "--out", str(tmp_path / "cfg"), "--config", str(tmp_path / "t.yaml")]) == 0
    # the unstamped Twist is timed by its log time, which the writer set to the stamp: same run
    assert _ate(tmp_path / "opt") == pytest.approx(_ate(tmp_path / "own"), rel=1e-9)
    assert _ate(tmp_path / "cfg") == pytest.approx(_ate(tmp_path / "own"), rel=1e-9)
    saved = yaml.safe_load((tmp_path / "opt" / "config.yaml").read_text())
    assert saved["topics"] == ROBOT
    # the saved config.yaml is accepted back and maps the topics again
    assert main([*base, str(dirs / "robot"), "--out", str(tmp_path / "again"),
                 "--config", str(tmp_path / "opt" / "config.yaml")]) == 0
    assert _ate(tmp_path / "again") == pytest.approx(_ate(tmp_path / "own"), rel=1e-9)


def test_a_missing_topic_lists_what_the_bag_has(dirs, tmp_path, capsys):
    assert main(["run", str(dirs / "robot"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "required topic(s) missing or empty: /imu" in err
    assert "/imu/data (sensor_msgs/msg/Imu" in err and "--topic ROLE=NAME" in err
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


@pytest.mark.parametrize("bad, message", [
    (["--topic", "imu"], "ROLE=NAME"),
    (["--topic", "lidar=/points"], "unknown role(s) ['lidar']"),
    (["--topic", "imu=imu/data"], "starting with '/'"),
    (["--topic", "imu=/a", "--topic", "imu=/b"], "twice"),
    (["--topic", "imu=/x", "--topic", "wheel_odom=/x"], "named for several roles"),
])
def test_bad_topic_maps_are_named(dirs, tmp_path, capsys, bad, message):
    assert main(["run", str(dirs / "robot"), "--out", str(tmp_path / "o"), *bad]) == 2
    assert message in capsys.readouterr().err


def test_topic_map_roles():
    t = bag_topics(parse_topic_options(["imu=/imu/data", "left_image=/stereo/left/image_raw/compressed"]))
    assert t.imu == "/imu/data" and t.left_image == "/stereo/left/image_raw/compressed" and t.rocks == "/rocks"
    with pytest.raises(ConfigError, match="roles are cmd_vel, imu"):
        bag_topics({"camera": "/c"})

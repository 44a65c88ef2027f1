"""fgslam.io.bag_reader: bag forms, other tools' bags, malformed bags, counted stamp repairs."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import StoragePlugin
from scipy.spatial.transform import Rotation

from fgslam.errors import BagError
from fgslam.io import BagReaderConfig, read_bag
from fgslam.io.synthetic import SyntheticStreamConfig, synthetic_stream
from reloc.bag_spec import TopicNames, typestore
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    RockObservations,
    WheelOdometry,
    sort_key,
)
from sim.bag_writer import write_bag


@pytest.fixture(scope="module")
def stream() -> list:
    cfg = SyntheticStreamConfig(duration_s=2.0, rocks_per_frame=5.0)
    return synthetic_stream(cfg, np.random.default_rng(3))


def _close(a, b) -> bool:
    """Same type and values; quaternions may differ by re-normalisation (ulps)."""
    return type(a) is type(b) and all(
        np.allclose(getattr(a, k), getattr(b, k), rtol=1e-15, atol=1e-15) for k in a.__slots__
    )


def _same_stream(a: list, b: list) -> bool:
    return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))


# --- bag forms ------------------------------------------------------------------------------


def test_directory_mcap_file_and_bare_directory_read_alike(tmp_path, stream):
    bag = tmp_path / "bag"
    write_bag(bag, stream)
    (mcap,) = bag.glob("*.mcap")
    assert _same_stream(read_bag(bag).measurements, stream)
    assert _same_stream(read_bag(mcap).measurements, stream)
    assert _same_stream(read_bag(bag / "metadata.yaml").measurements, stream)
    (bag / "metadata.yaml").unlink()  # a directory holding just one .mcap still reads
    assert _same_stream(read_bag(bag).measurements, stream)


def test_wheel_odom_replaces_cmd_vel_and_ground_truth_is_optional(tmp_path, stream):
    kept = [m for m in stream if not isinstance(m, (CmdVel, GroundTruthPose))]
    write_bag(tmp_path / "bag", kept)
    got = read_bag(tmp_path / "bag")
    assert _same_stream(got.measurements, kept)
    assert set(got.report.topics) == {"/wheel_odom", "/imu", "/rocks"}


# --- bags written by other tools --------------------------------------------------------------


def _header(ns: int, frame: str):
    T = typestore().types
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame
    )


def _vec(T, x=0.0, y=0.0, z=0.0):
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _imu(ns: int, gyro_z: float = 0.0, quat=(0.0, 0.0, 0.0, 1.0)):
    T = typestore().types
    return T["sensor_msgs/msg/Imu"](
        header=_header(ns, "imu_link"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
        orientation_covariance=np.zeros(9),
        angular_velocity=_vec(T, z=gyro_z),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vec(T, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def _twist(v: float, w: float):
    T = typestore().types
    return T["geometry_msgs/msg/Twist"](linear=_vec(T, x=v), angular=_vec(T, z=w))


def _rocks(ns: int, frame: str, centres: np.ndarray, sizes: np.ndarray, with_cov: bool):
    T = typestore().types
    dets = []
    for c, d in zip(centres, sizes):
        cov = np.zeros((6, 6))
        if with_cov:
            cov[:3, :3] = np.diag([0.01, 0.02, 0.03])
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=c[0], y=c[1], z=c[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        dets.append(
            T["vision_msgs/msg/Detection3D"](
                header=_header(ns, ""),  # frame left empty: the array header names it
                results=[
                    T["vision_msgs/msg/ObjectHypothesisWithPose"](
                        hypothesis=T["vision_msgs/msg/ObjectHypothesis"](
                            class_id="boulder", score=0.8
                        ),
                        pose=T["geometry_msgs/msg/PoseWithCovariance"](
                            pose=pose, covariance=cov.ravel()
                        ),
                    )
                ],
                bbox=T["vision_msgs/msg/BoundingBox3D"](center=pose, size=_vec(T, d, 0.5 * d, 0.0)),
                id="",
            )
        )
    return T["vision_msgs/msg/Detection3DArray"](header=_header(ns, frame), detections=dets)


def _write_raw(path: Path, messages, storage=StoragePlugin.MCAP) -> Path:
    """A bag as another recorder would write it: given (topic, type, log_ns, msg), uncompressed."""
    ts = typestore()
    conns = {}
    with Writer(path, version=8, storage_plugin=storage) as w:
        for topic, msgtype, ns, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_cdr(msg, msgtype))
    return path


T_BASE_CAM = np.eye(4)
T_BASE_CAM[:3, :3] = Rotation.from_euler("xyz", [-np.pi / 2 - 0.3, 0.0, -np.pi / 2]).as_matrix()
T_BASE_CAM[:3, 3] = [0.3, 0.05, 1.1]


def _other_tool_messages(nan_at: int | None = None):
    centres = np.array([[0.5, 0.2, 4.0], [-1.0, 0.3, 7.5]])  # camera optical frame
    msgs = []
    for k in range(10):
        ns = 5 * 10**9 + k * 50_000_000
        gyro = float("nan") if k == nan_at else 0.01 * k
        msgs.append(("/imu", "sensor_msgs/msg/Imu", ns, _imu(ns, gyro)))
        msgs.append(("/cmd_vel", "geometry_msgs/msg/Twist", ns + 1000, _twist(0.1 * k, 0.0)))
        if k % 5 == 0:
            msgs.append(
                (
                    "/rocks",
                    "vision_msgs/msg/Detection3DArray",
                    ns,
                    _rocks(ns, "camera_optical", centres, np.array([0.4, 0.9]), with_cov=False),
                )
            )
    return msgs, centres


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_other_tool_bag_camera_frame_unstamped_twist(tmp_path, storage):
    msgs, centres = _other_tool_messages()
    bag = _write_raw(tmp_path / "bag", msgs, storage)
    cfg = BagReaderConfig(default_rock_sigma_m=0.1)
    got = read_bag(bag, camera_frames={"camera_optical": T_BASE_CAM}, config=cfg)
    cmds = got.of_type(CmdVel)
    assert [c.v_mps for c in cmds] == pytest.approx([0.1 * k for k in range(10)])
    assert cmds[3].t == (5 * 10**9 + 3 * 50_000_000 + 1000) / 1e9  # log time stands in for a stamp
    assert got.report.topics["/cmd_vel"].n_log_stamped == 10
    frames = got.of_type(RockObservations)
    assert len(frames) == 2 and len(frames[0]) == 2
    expected = centres @ T_BASE_CAM[:3, :3].T + T_BASE_CAM[:3, 3]
    np.testing.assert_allclose(frames[0].xyz_base_m, expected, atol=1e-12)
    np.testing.assert_allclose(
        frames[0].cov_base_m2, np.tile(np.eye(3) * 0.01, (2, 1, 1)), atol=1e-15
    )
    np.testing.assert_array_equal(frames[0].size_m, [0.4, 0.9])  # largest bbox extent
    np.testing.assert_array_equal(frames[0].score, [0.8, 0.8])
    assert got.measurements == sorted(got.measurements, key=sort_key)


def test_camera_frame_errors(tmp_path):
    msgs, _ = _other_tool_messages()
    bag = _write_raw(tmp_path / "bag", msgs)
    with pytest.raises(BagError, match=r"topic /rocks: .*frame 'camera_optical'"):
        read_bag(bag, config=BagReaderConfig(default_rock_sigma_m=0.1))
    with pytest.raises(BagError, match="positive-definite position covariance"):
        read_bag(bag, camera_frames={"camera_optical": T_BASE_CAM}, repair=False)
    with pytest.raises(BagError, match="not a rotation"):
        read_bag(bag, camera_frames={"camera_optical": np.diag([2.0, 1, 1, 1])})


def test_nan_message_dropped_counted_or_raised(tmp_path, caplog):
    msgs, _ = _other_tool_messages(nan_at=4)
    bag = _write_raw(tmp_path / "bag", msgs)
    kw = {
        "camera_frames": {"camera_optical": T_BASE_CAM},
        "config": BagReaderConfig(default_rock_sigma_m=0.1),
    }
    with caplog.at_level(logging.WARNING, logger="fgslam.io.bag_reader"):
        got = read_bag(bag, **kw)
    imu = got.report.topics["/imu"]
    assert (imu.n_messages, imu.n_kept, imu.n_nonfinite) == (10, 9, 1)
    assert all(np.isfinite(m.gyro_radps).all() for m in got.of_type(ImuSample))
    assert any(
        r.startswith("/imu: dropped 1 message(s) holding NaN/inf") for r in got.report.repairs
    )
    assert any("NaN" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
    with pytest.raises(BagError, match=r"topic /imu: message 5 .*NaN"):
        read_bag(bag, repair=False, **kw)


def test_required_topic_with_no_usable_message(tmp_path):
    msgs, _ = _other_tool_messages()
    # ROS convention for "no orientation": an all-zero quaternion; no ImuSample can come of it.
    msgs = [
        (t, ty, ns, _imu(ns, quat=(0.0, 0.0, 0.0, 0.0)) if t == "/imu" else m)
        for t, ty, ns, m in msgs
    ]
    bag = _write_raw(tmp_path / "bag", msgs)
    with pytest.raises(BagError, match=r"topic /imu: none of its 10 message\(s\) is usable .*unit"):
        read_bag(
            bag,
            camera_frames={"camera_optical": T_BASE_CAM},
            config=BagReaderConfig(default_rock_sigma_m=0.1),
        )


def test_rock_class_filter(tmp_path):
    msgs, _ = _other_tool_messages()
    bag = _write_raw(tmp_path / "bag", msgs)
    kw = {"camera_frames": {"camera_optical": T_BASE_CAM}}
    cfg = BagReaderConfig(default_rock_sigma_m=0.1, rock_class_ids=("rock",))
    frames = read_bag(bag, config=cfg, **kw).of_type(RockObservations)
    assert [len(f) for f in frames] == [0, 0]  # "boulder" hypotheses are not rocks here
    cfg = replace(cfg, rock_class_ids=("rock", "boulder"))
    assert [len(f) for f in read_bag(bag, config=cfg, **kw).of_type(RockObservations)] == [2, 2]


# --- malformed bags ---------------------------------------------------------------------------


def test_missing_required_topic(tmp_path, stream):
    bag = tmp_path / "bag"
    write_bag(bag, [m for m in stream if not isinstance(m, ImuSample)])
    with pytest.raises(BagError, match=r"bag .*bag: required topic\(s\) missing or empty: /imu;"):
        read_bag(bag)
    bag2 = tmp_path / "bag2"
    write_bag(bag2, [m for m in stream if not isinstance(m, (CmdVel, WheelOdometry))])
    with pytest.raises(BagError, match="/cmd_vel or /wheel_odom"):
        read_bag(bag2)


def test_wrong_message_type_on_topic(tmp_path, stream):
    bag = tmp_path / "bag"
    write_bag(bag, stream, topics=TopicNames(imu="/a", ground_truth="/b"))
    with pytest.raises(
        BagError, match=r"topic /b has type nav_msgs/msg/Odometry, expected sensor_msgs/msg/Imu"
    ):
        read_bag(bag, TopicNames(imu="/b", ground_truth="/a"))


@pytest.mark.parametrize(
    "name, content, needle",
    [
        ("garbage.mcap", b"\x00garbage" * 100, "cannot be opened"),
        ("notes.txt", b"hello", "not a ROS 2 bag"),
        ("empty.mcap", b"", "cannot be opened"),
    ],
)
def test_garbage_files(tmp_path, name, content, needle):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(BagError, match=needle) as exc:
        read_bag(path)
    assert str(path) in str(exc.value)


def test_missing_path_and_garbage_metadata(tmp_path):
    with pytest.raises(BagError, match="does not exist"):
        read_bag(tmp_path / "nope")
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [this is: not valid")
    with pytest.raises(BagError, match="cannot be opened"):
        read_bag(bag)
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        read_bag(tmp_path)


@pytest.mark.parametrize("keep", [0.5, 0.97])
def test_truncated_bag(tmp_path, stream, keep):
    bag = tmp_path / "bag"
    write_bag(bag, stream)
    (mcap,) = bag.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(BagError, match="mcap recover") as exc:
        read_bag(bag)
    assert str(bag) in str(exc.value)


@pytest.mark.parametrize("where", [0.2, 0.5])
def test_corrupt_chunk(tmp_path, stream, where):
    bag = tmp_path / "bag"
    write_bag(bag, stream)
    (mcap,) = bag.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    i = int(len(data) * where)  # inside the (single) compressed chunk
    data[i : i + 16] = b"\xff" * 16
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match="corrupt bag") as exc:
        read_bag(bag)
    assert str(bag) in str(exc.value)


# --- stamps: duplicates, conflicts, out of order ----------------------------------------------


def test_exact_duplicates_dropped_and_counted(tmp_path, stream, caplog):
    imu = [m for m in stream if isinstance(m, ImuSample)]
    frames = [m for m in stream if isinstance(m, RockObservations)]
    bag = tmp_path / "bag"
    write_bag(bag, [*stream, imu[3], imu[7], frames[1]])  # re-sent messages
    with caplog.at_level(logging.WARNING, logger="fgslam.io.bag_reader"):
        got = read_bag(bag)
    assert _same_stream(got.measurements, stream)
    rep = got.report.topics
    assert (rep["/imu"].n_duplicates, rep["/imu"].n_kept) == (2, len(imu))
    assert rep["/rocks"].n_duplicates == 1 and rep["/cmd_vel"].n_repairs == 0
    assert got.report.n_repairs == 2 + 1
    assert "/imu: dropped 2 exact duplicate message(s)" in got.report.repairs
    assert sum("duplicate" in r.getMessage() for r in caplog.records) == 2
    with pytest.raises(BagError, match=r"topic /imu: a message shares its stamp 1100000000 ns with an earlier one \(duplicate\)"):
        read_bag(bag, repair=False)


def test_duplicates_in_place_raise_without_repair(tmp_path, stream):
    cmds = [m for m in stream if isinstance(m, CmdVel)]
    i = stream.index(cmds[5])
    bag = tmp_path / "bag"
    write_bag(bag, [*stream[: i + 1], cmds[5], *stream[i + 1 :]])
    assert read_bag(bag).report.topics["/cmd_vel"].n_duplicates == 1
    with pytest.raises(BagError, match=r"topic /cmd_vel: a message shares its stamp .* \(duplicate\)"):
        read_bag(bag, repair=False)


def test_conflicting_same_stamp_keeps_first_recorded(tmp_path, stream):
    cmds = [m for m in stream if isinstance(m, CmdVel)]
    i = stream.index(cmds[5])
    clash = replace(cmds[5], v_mps=cmds[5].v_mps + 1.0)
    bag = tmp_path / "bag"
    write_bag(bag, [*stream[: i + 1], clash, *stream[i + 1 :]])
    got = read_bag(bag)
    assert got.report.topics["/cmd_vel"].n_conflicts == 1
    assert _same_stream(got.measurements, stream)
    with pytest.raises(BagError, match=r"\(conflicting\)"):
        read_bag(bag, repair=False)


def test_shuffled_write_reads_sorted_without_repairs(tmp_path, stream):
    """MCAP readers yield by log time; with log time == stamp a shuffled write needs no repair."""
    shuffled = list(stream)
    np.random.default_rng(0).shuffle(shuffled)
    write_bag(tmp_path / "bag", shuffled)
    got = read_bag(tmp_path / "bag", repair=False)
    assert _same_stream(got.measurements, stream) and got.report.n_repairs == 0


def test_stamps_out_of_log_time_order_sorted_and_counted(tmp_path, caplog):
    """A recorder logs in arrival order; stamps that go backwards are sorted and counted."""
    msgs, _ = _other_tool_messages()
    stamps = [_imu_stamp(m) for topic, _, _, m in msgs if topic == "/imu"]
    # Swap the header stamps of IMU samples 3 and 4 (and 7 and 8); log times stay in order.
    order = {3: 4, 4: 3, 7: 8, 8: 7}
    k = 0
    out = []
    for topic, msgtype, ns, m in msgs:
        if topic == "/imu":
            m = _imu(stamps[order.get(k, k)], gyro_z=0.01 * k)
            k += 1
        out.append((topic, msgtype, ns, m))
    bag = _write_raw(tmp_path / "bag", out)
    kw = {
        "camera_frames": {"camera_optical": T_BASE_CAM},
        "config": BagReaderConfig(default_rock_sigma_m=0.1),
    }
    with caplog.at_level(logging.WARNING, logger="fgslam.io.bag_reader"):
        got = read_bag(bag, **kw)
    imu = got.report.topics["/imu"]
    assert (imu.n_reordered, imu.n_kept, imu.n_repairs) == (2, 10, 2)
    assert "/imu: sorted 2 message(s) recorded out of stamp order" in got.report.repairs
    samples = got.of_type(ImuSample)
    assert [s.t for s in samples] == sorted(stamps[i] / 1e9 for i in range(10))
    # the sample recorded 4th carries stamp 3's time: sorting by stamp puts its gyro at index 3
    assert [round(s.gyro_radps[2] / 0.01) for s in samples] == [0, 1, 2, 4, 3, 5, 6, 8, 7, 9]
    assert any("out of stamp order" in r.getMessage() for r in caplog.records)
    with pytest.raises(BagError, match=r"topic /imu: message 5 stamped earlier .* \(out of order\)"):
        read_bag(bag, repair=False, **kw)


def _imu_stamp(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def _identical(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        type(x) is type(y) and all(np.array_equal(getattr(x, k), getattr(y, k)) for k in x.__slots__)
        for x, y in zip(a, b))


def test_landmark_frames_read_alike_parsed_or_deserialized(tmp_path, stream, monkeypatch):
    """The rock and crater frames parsed from their bytes (reloc.detections) give the very
    measurements, reports and errors of rosbags' deserializer."""
    from fgslam.io import bag_merge

    bag = tmp_path / "bag"
    write_bag(bag, stream)
    msgs, _ = _other_tool_messages()
    other = _write_raw(tmp_path / "other", msgs)
    kw = {"camera_frames": {"camera_optical": T_BASE_CAM}, "config": BagReaderConfig(default_rock_sigma_m=0.1)}

    def reads():
        errors = []
        for call in (lambda: read_bag(other, config=BagReaderConfig(default_rock_sigma_m=0.1)),
                     lambda: read_bag(other, camera_frames=kw["camera_frames"], repair=False)):
            with pytest.raises(BagError) as info:
                call()
            errors.append(str(info.value))
        return read_bag(bag), read_bag(other, **kw), errors

    used = []
    chosen = bag_merge.usable_parser
    monkeypatch.setattr(bag_merge, "usable_parser", lambda *a: used.append(chosen(*a)) or used[-1])
    parsed = reads()
    assert any(p is not None for p in used)
    monkeypatch.setattr(bag_merge, "usable_parser", lambda *a: None)
    deserialized = reads()
    for got, ref in zip(parsed[:2], deserialized[:2]):
        assert _identical(got.measurements, ref.measurements)
        assert got.report == ref.report
    assert parsed[2] == deserialized[2]
    assert sum(len(m) for m in parsed[0].measurements if isinstance(m, RockObservations)) > 10

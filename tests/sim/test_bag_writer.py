"""Bags written by sim.bag_writer read back intact by our reader, by rosbags and by mcap-ros2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fgslam.io import read_bag
from fgslam.io.synthetic import SyntheticStreamConfig, synthetic_stream
from reloc.bag_spec import BagEncoding, TopicNames
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    RockObservations,
    WheelOdometry,
)
from sim.bag_writer import BagWriteError, stamp_ns, write_bag

TOPIC_OF = {
    CmdVel: "/cmd_vel",
    ImuSample: "/imu",
    WheelOdometry: "/wheel_odom",
    GroundTruthPose: "/ground_truth",
    RockObservations: "/rocks",
}


@pytest.fixture(scope="module")
def stream() -> list:
    return synthetic_stream(SyntheticStreamConfig(duration_s=4.0), np.random.default_rng(7))


@pytest.fixture(scope="module")
def bag(stream, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bags") / "run"
    summary = write_bag(path, stream)
    expected = {topic: sum(type(m) is cls for m in stream) for cls, topic in TOPIC_OF.items()}
    assert summary.counts == expected
    assert summary.n_bytes == sum(p.stat().st_size for p in path.iterdir())
    assert summary.t_start == stream[0].t and summary.t_end == stream[-1].t
    return path


def _by_topic(stream) -> dict[str, list]:
    out: dict[str, list] = {t: [] for t in TOPIC_OF.values()}
    for m in stream:
        out[TOPIC_OF[type(m)]].append(m)
    return out


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _xyz(v) -> list[float]:
    return [v.x, v.y, v.z]


def _xyzw(q) -> list[float]:
    return [q.x, q.y, q.z, q.w]


def check_message(topic: str, m, msg) -> None:
    """Every field of ``msg`` (any deserializer's object) against the measurement ``m``."""
    assert _stamp(msg.header) == stamp_ns(m.t)
    enc = BagEncoding()
    if topic == "/cmd_vel":
        assert msg.header.frame_id == "base_link"
        assert (msg.twist.linear.x, msg.twist.angular.z) == (m.v_mps, m.yaw_rate_radps)
        assert _xyz(msg.twist.linear)[1:] == [0, 0] and _xyz(msg.twist.angular)[:2] == [0, 0]
    elif topic == "/imu":
        assert _xyzw(msg.orientation) == list(m.quat_xyzw)
        assert _xyz(msg.angular_velocity) == list(m.gyro_radps)
        assert _xyz(msg.linear_acceleration) == list(m.accel_mps2)
        np.testing.assert_allclose(
            np.reshape(msg.orientation_covariance, (3, 3)),
            np.diag(np.square(enc.imu_orientation_sigma_rad)),
        )
        assert (
            np.reshape(msg.angular_velocity_covariance, (3, 3))[2, 2] == enc.imu_gyro_sigma_radps**2
        )
        assert (
            np.reshape(msg.linear_acceleration_covariance, (3, 3))[0, 0]
            == enc.imu_accel_sigma_mps2**2
        )
    elif topic == "/wheel_odom":
        assert msg.child_frame_id == "base_link"
        assert (msg.twist.twist.linear.x, msg.twist.twist.angular.z) == (m.v_mps, m.yaw_rate_radps)
        tw = np.reshape(msg.twist.covariance, (6, 6))
        assert (
            tw[0, 0] == enc.wheel_v_sigma_mps**2 and tw[5, 5] == enc.wheel_yaw_rate_sigma_radps**2
        )
    elif topic == "/ground_truth":
        assert (msg.header.frame_id, msg.child_frame_id) == ("world", "base_link")
        assert _xyz(msg.pose.pose.position) == list(m.position_m)
        assert _xyzw(msg.pose.pose.orientation) == list(m.quat_xyzw)
    elif topic == "/rocks":
        assert msg.header.frame_id == "base_link"
        assert len(msg.detections) == len(m)
        for i, det in enumerate(msg.detections):
            assert det.header.frame_id == "base_link" and _stamp(det.header) == stamp_ns(m.t)
            assert _xyz(det.bbox.center.position) == list(m.xyz_base_m[i])
            assert _xyzw(det.bbox.center.orientation) == [0, 0, 0, 1]
            assert _xyz(det.bbox.size) == [m.size_m[i]] * 3
            assert len(det.results) == 1
            res = det.results[0]
            assert res.hypothesis.class_id == "rock" and res.hypothesis.score == m.score[i]
            assert _xyz(res.pose.pose.position) == list(m.xyz_base_m[i])
            cov6 = np.reshape(res.pose.covariance, (6, 6))
            np.testing.assert_array_equal(cov6[:3, :3], m.cov_base_m2[i])
            np.testing.assert_array_equal(cov6[3:, 3:], np.eye(3) * enc.rock_rotation_var)
            assert not np.any(cov6[:3, 3:]) and not np.any(cov6[3:, :3])
    else:  # pragma: no cover
        raise AssertionError(topic)


def test_our_reader_gets_every_field_back(bag, stream):
    got = read_bag(bag)
    assert got.report.n_repairs == 0 and got.report.repairs == ()
    assert len(got.measurements) == len(stream)
    for a, b in zip(stream, got.measurements):
        assert type(a) is type(b) and a.t == b.t
        for name in a.__slots__:
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=1e-15, atol=0)
    frames = got.of_type(RockObservations)
    assert any(len(f) == 0 for f in frames), "an empty rock frame must survive the round trip"
    assert sum(len(f) for f in frames) > 50


def test_rosbags_reads_every_field(bag, stream):
    from rosbags.highlevel import AnyReader

    expected = _by_topic(stream)
    seen: dict[str, int] = {t: 0 for t in expected}
    with AnyReader([bag]) as reader:  # no typestore: the bag's embedded schemas suffice
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/cmd_vel": "geometry_msgs/msg/TwistStamped",
            "/imu": "sensor_msgs/msg/Imu",
            "/wheel_odom": "nav_msgs/msg/Odometry",
            "/ground_truth": "nav_msgs/msg/Odometry",
            "/rocks": "vision_msgs/msg/Detection3DArray",
        }
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            m = expected[conn.topic][seen[conn.topic]]
            assert log_ns == stamp_ns(m.t)
            check_message(conn.topic, m, msg)
            seen[conn.topic] += 1
    assert seen == {t: len(v) for t, v in expected.items()}


def test_mcap_ros2_reads_every_field_and_chunks_are_zstd(bag, stream):
    # mcap_ros2.reader.read_ros2_messages is deprecated in favour of this same decoder factory.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap_file,) = bag.glob("*.mcap")
    expected = _by_topic(stream)
    seen: dict[str, int] = {t: 0 for t in expected}
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, ros_msg in reader.iter_decoded_messages():
            m = expected[channel.topic][seen[channel.topic]]
            assert message.log_time == stamp_ns(m.t)
            check_message(channel.topic, m, ros_msg)
            seen[channel.topic] += 1
        summary = reader.get_summary()
    assert seen == {t: len(v) for t, v in expected.items()}

    assert summary is not None and summary.chunk_indexes
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert all(c.compressed_size < c.uncompressed_size for c in summary.chunk_indexes)
    schemas = {s.name: s.encoding for s in summary.schemas.values()}
    assert schemas["vision_msgs/msg/Detection3DArray"] == "ros2msg"


def test_custom_topics_and_base_frame(tmp_path, stream):
    topics = TopicNames(
        cmd_vel="/rover/cmd",
        imu="/rover/imu",
        wheel_odom="/rover/odom",
        rocks="/stereo/rocks",
        ground_truth="/sim/gt",
    )
    path = tmp_path / "bag"
    summary = write_bag(path, stream[:200], topics=topics, frame_id_base="rover_base")
    assert set(summary.counts) <= {
        topics.cmd_vel,
        topics.imu,
        topics.wheel_odom,
        topics.rocks,
        topics.ground_truth,
    }
    from fgslam.io import BagReaderConfig

    got = read_bag(path, topics, config=BagReaderConfig(base_frame="rover_base"))
    assert len(got.measurements) == 200
    with pytest.raises(Exception, match="frame 'rover_base'"):
        read_bag(path, topics)  # base_link reader: rover_base is an unknown frame


def test_overwrite_rules(tmp_path, stream):
    path = tmp_path / "bag"
    write_bag(path, stream[:50])
    with pytest.raises(BagWriteError, match="exists"):
        write_bag(path, stream[:50])
    assert write_bag(path, stream[:60], overwrite=True).n_messages == 60
    other = tmp_path / "notabag"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    with pytest.raises(BagWriteError, match="non-bag entries"):
        write_bag(other, stream[:10], overwrite=True)
    assert (other / "precious.txt").exists()


def test_bad_measurement_leaves_no_partial_bag(tmp_path, stream):
    path = tmp_path / "bag"
    with pytest.raises(BagWriteError, match="unknown type"):
        write_bag(path, [*stream[:20], "not a measurement"])
    assert not path.exists()


def test_negative_time_and_bad_topic_names(tmp_path):
    with pytest.raises(BagWriteError, match="negative time"):
        write_bag(tmp_path / "bag", [CmdVel(-0.5, 0.1, 0.0)])
    assert not (tmp_path / "bag").exists()
    with pytest.raises(ValueError, match="distinct"):
        TopicNames(imu="/cmd_vel")
    with pytest.raises(ValueError, match="non-empty"):
        TopicNames(rocks="")


def test_stamp_ns_rounds_to_nearest_nanosecond():
    assert stamp_ns(1.0000000004) == 1_000_000_000
    assert stamp_ns(1.0000000006) == 1_000_000_001
    assert stamp_ns(1_700_000_000.123456789) == 1_700_000_000_123_456_768  # float64 spacing


def test_fast_encoders_match_rosbags_and_a_mismatch_falls_back(stream, tmp_path, monkeypatch, caplog):
    """The precompiled encoders write the bytes rosbags writes (same bag either way); if they ever
    disagree on the sample messages, the writer says so and uses rosbags."""
    import sim.bag_fast as fast
    import sim.bag_writer as bw

    a = write_bag(tmp_path / "fast", stream)
    monkeypatch.setattr(bw, "_fast_encoder", lambda enc, encoding: None)
    b = write_bag(tmp_path / "slow", stream)
    monkeypatch.undo()
    assert a.counts == b.counts
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "fast"]) as fa, AnyReader([tmp_path / "slow"]) as sl:
        raw_a = [(c.topic, t, bytes(d)) for c, t, d in fa.messages()]
        raw_b = [(c.topic, t, bytes(d)) for c, t, d in sl.messages()]
    assert raw_a == raw_b  # byte for byte
    ra = read_bag(tmp_path / "fast")
    monkeypatch.setattr(fast.FastEncoder, "imu", lambda self, m, ns: b"\x00\x01\x00\x00broken")
    with caplog.at_level("WARNING"):
        c = write_bag(tmp_path / "fallback", stream)
    assert "disagree with rosbags" in caplog.text
    assert c.counts == a.counts
    assert len(read_bag(tmp_path / "fallback").measurements) == len(ra.measurements)

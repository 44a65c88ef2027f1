"""Detection3DArray straight from CDR bytes: the same arrays as rosbags' deserializer gives, or
None (never an exception) for bytes it does not read."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from reloc.bag_spec import typestore
from reloc.detections import (
    DETECTIONS_PARSER,
    DETECTIONS_TYPE,
    Detections,
    parse_detection3d_array,
    same_layout,
)

TS = typestore()
T = TS.types

floats = st.one_of(st.sampled_from([0.0, -0.0, 1.5, -2.25e-3, float("nan"), float("inf")]),
                   st.floats(allow_nan=True, allow_infinity=True, width=64))
names = st.text(max_size=12)  # empty, ASCII and beyond (UTF-8 of 1-4 bytes: every alignment)


def _pose(v):
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6]),
    )


def _header(sec: int, nsec: int, frame: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame)


@st.composite
def results(draw):
    return T["vision_msgs/msg/ObjectHypothesisWithPose"](
        hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=draw(names), score=draw(floats)),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(draw(st.lists(floats, min_size=7, max_size=7))),
            covariance=np.resize(np.array(draw(st.lists(floats, min_size=1, max_size=6))), 36),
        ),
    )


@st.composite
def detection(draw):
    return T["vision_msgs/msg/Detection3D"](
        header=_header(draw(st.integers(-2**31, 2**31 - 1)), draw(st.integers(0, 999_999_999)), draw(names)),
        results=draw(st.lists(results(), max_size=3)),
        bbox=T["vision_msgs/msg/BoundingBox3D"](
            center=_pose(draw(st.lists(floats, min_size=7, max_size=7))),
            size=T["geometry_msgs/msg/Vector3"](x=draw(floats), y=draw(floats), z=draw(floats)),
        ),
        id=draw(names),
    )


@st.composite
def arrays(draw):
    return T[DETECTIONS_TYPE](
        header=_header(draw(st.integers(-2**31, 2**31 - 1)), draw(st.integers(0, 999_999_999)), draw(names)),
        detections=draw(st.lists(detection(), max_size=5)),
    )


def _same(a: Detections, b: Detections) -> bool:
    for name in Detections.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            if x.dtype != y.dtype or x.shape != y.shape or not np.array_equal(x, y, equal_nan=True):
                return False
        elif x != y:
            return False
    return True


def _cdr(msg, **kw) -> bytes:
    return bytes(TS.serialize_cdr(msg, DETECTIONS_TYPE, **kw))


def _rosbags(raw) -> Detections:
    return Detections.from_message(TS.deserialize_cdr(raw, DETECTIONS_TYPE))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays())
def test_parsed_bytes_equal_rosbags_message(msg):
    raw = _cdr(msg)
    got = parse_detection3d_array(raw)
    assert got is not None
    assert _same(got, _rosbags(raw))
    assert len(got) == len(msg.detections) and len(got.class_id) == sum(len(d.results) for d in msg.detections)
    assert _same(parse_detection3d_array(memoryview(raw)), got)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays(), st.data())
def test_damaged_bytes_give_none_or_what_rosbags_reads(msg, data):
    """Cut short, grown, or with bytes overwritten (lengths and counts among them): never an
    exception; whatever the parser reads, rosbags reads the same."""
    raw = bytearray(_cdr(msg))
    how = data.draw(st.sampled_from(["cut", "grow", "poke"]))
    if how == "cut":
        raw = raw[:data.draw(st.integers(0, len(raw) - 1))]
    elif how == "grow":
        raw += bytes(data.draw(st.integers(1, 16)))
    else:
        for _ in range(data.draw(st.integers(1, 4))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    got = parse_detection3d_array(bytes(raw))
    if got is not None:
        assert _same(got, _rosbags(bytes(raw)))


def test_padding_and_cut_bounds():
    """The 3 bytes of padding rosbag2 may leave after the last field are accepted, a fourth is
    not (rosbags' own rule); a message cut anywhere is not read."""
    msg = T[DETECTIONS_TYPE](header=_header(1, 2, "base_link"), detections=[])
    raw = _cdr(msg)
    for pad in range(4):
        assert parse_detection3d_array(raw + bytes(pad)) is not None
    assert parse_detection3d_array(raw + bytes(8)) is None
    for k in range(len(raw)):
        assert parse_detection3d_array(raw[:k]) is None


def test_big_endian_and_other_encapsulations_left_to_rosbags():
    msg = T[DETECTIONS_TYPE](header=_header(3, 4, "cam"), detections=[])
    raw = _cdr(msg, little_endian=False)
    assert parse_detection3d_array(raw) is None
    assert _rosbags(raw).frame_id == "cam"  # rosbags still reads it
    assert parse_detection3d_array(b"") is None
    assert parse_detection3d_array(b"\x00\x03\x00\x00" + raw[4:]) is None


FOXY_DETECTION3D = """
std_msgs/Header header
vision_msgs/ObjectHypothesisWithPose[] results
vision_msgs/BoundingBox3D bbox
sensor_msgs/PointCloud2 source_cloud
bool is_tracking
string tracking_id
"""


def test_parser_only_for_fgslams_definitions():
    """vision_msgs 2.x (Foxy) lays Detection3D out differently: a bag defining it so is read by rosbags."""
    assert same_layout(TS, TS) and DETECTIONS_PARSER.accepts(TS)
    foxy = get_typestore(Stores.ROS2_JAZZY)
    from reloc.bag_spec import register_vision_msgs

    foxy.register(get_types_from_msg(FOXY_DETECTION3D, "vision_msgs/msg/Detection3D"))
    register_vision_msgs(foxy)  # the rest of vision_msgs as fgslam has them
    assert not DETECTIONS_PARSER.accepts(foxy)
    assert not DETECTIONS_PARSER.accepts(get_typestore(Stores.ROS2_JAZZY))  # no vision_msgs at all


@pytest.mark.parametrize("n", [0, 1, 40])
def test_typical_frame(n):
    """A frame as the simulator writes it: one 'rock' hypothesis per detection, ids empty."""
    rng = np.random.default_rng(n)
    dets = []
    for _ in range(n):
        v = rng.normal(size=7)
        cov = np.zeros(36)
        cov[[0, 7, 14]] = rng.uniform(0.01, 0.1, 3)
        dets.append(T["vision_msgs/msg/Detection3D"](
            header=_header(5, 6, "base_link"),
            results=[T["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id="rock", score=0.9),
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(v), covariance=cov))],
            bbox=T["vision_msgs/msg/BoundingBox3D"](center=_pose(v), size=T["geometry_msgs/msg/Vector3"](x=0.5, y=0.5, z=0.5)),
            id=""))
    raw = _cdr(T[DETECTIONS_TYPE](header=_header(5, 6, "base_link"), detections=dets))
    got = parse_detection3d_array(raw)
    assert got.stamp_ns == 5_000_000_006 and got.frame_id == "base_link" and len(got) == n
    assert got.center.shape == (n, 7) and got.covariance.shape == (n, 36)
    assert _same(got, _rosbags(raw))

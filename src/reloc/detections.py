"""``vision_msgs/Detection3DArray`` as arrays: the form the landmark kinds' bag layers decode
(:mod:`reloc.rock_bag`, :mod:`reloc.crater_bag`), made from a deserialized message or straight
from its CDR bytes.

rosbags deserialises a Detection3DArray as ~14 Python objects per detection (~60 us each: 7 ms
for a frame of 110 rocks, most of a kilometre bag's read time). :func:`parse_detection3d_array`
walks the CDR bytes once, keeping the strings and the offsets of the float64 runs, and gathers
the floats with one numpy index (~15x faster). It reads the vision_msgs 4.x layout (ROS 2
Humble, Jazzy: :data:`reloc.bag_spec.VISION_MSGS`) only: :func:`same_layout` tells whether a
bag's embedded definitions are those; anything else it cannot read (big endian, a truncated or
inconsistent message) gives None, and the caller deserializes with rosbags, whose errors name
the problem.

CDR as rosbag2 records it (XCDR1): a 4-byte encapsulation header (``00 01``: little endian),
then the fields, each aligned to its size relative to the first byte after the header; a string
is a uint32 length (its NUL included) and the bytes; a sequence a uint32 count and the elements.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from reloc.bag_spec import ROCKS_TYPE, CdrParser, typestore

DETECTIONS_TYPE = ROCKS_TYPE
# the message types whose definitions the parser assumes (those of reloc.bag_spec's store)
LAYOUT_TYPES = (
    "vision_msgs/msg/Detection3DArray", "vision_msgs/msg/Detection3D", "vision_msgs/msg/ObjectHypothesisWithPose",
    "vision_msgs/msg/ObjectHypothesis", "vision_msgs/msg/BoundingBox3D", "std_msgs/msg/Header",
    "builtin_interfaces/msg/Time", "geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Vector3",
)
RESULT_F64 = 44  # a result's score, pose (position 3, orientation 4) and covariance 36
BBOX_F64 = 10  # a bounding box's centre pose (7) and size (3)


@dataclass(frozen=True)
class Detections:
    """One Detection3DArray (per detection: its header's frame id, bounding box and id; per
    hypothesis, flattened over the detections in order: its detection's index, class id,
    score, pose and covariance). The detections' own stamps are not kept (no layer reads them).

    ``center`` (n, 7): bbox centre position and orientation (x, y, z, w); ``size`` (n, 3);
    ``result_det`` (m,) int; ``pose`` (m, 7); ``covariance`` (m, 36), row-major 6 x 6."""

    stamp_ns: int
    frame_id: str
    det_frame: tuple[str, ...]
    center: np.ndarray
    size: np.ndarray
    ids: tuple[str, ...]
    result_det: np.ndarray
    class_id: tuple[str, ...]
    score: np.ndarray
    pose: np.ndarray
    covariance: np.ndarray

    def __len__(self) -> int:
        return len(self.det_frame)

    @classmethod
    def from_message(cls, msg) -> Detections:
        """The arrays of a deserialized Detection3DArray (rosbags' or any object with its fields)."""
        dets = list(msg.detections)
        results = [(i, r) for i, d in enumerate(dets) for r in d.results]

        def pose7(p):
            return (p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                    p.orientation.z, p.orientation.w)

        stamp = msg.header.stamp
        return cls(
            stamp_ns=int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
            frame_id=msg.header.frame_id,
            det_frame=tuple(d.header.frame_id for d in dets),
            center=np.array([pose7(d.bbox.center) for d in dets], dtype=float).reshape(-1, 7),
            size=np.array([(d.bbox.size.x, d.bbox.size.y, d.bbox.size.z) for d in dets], dtype=float).reshape(-1, 3),
            ids=tuple(d.id for d in dets),
            result_det=np.array([i for i, _ in results], dtype=np.int64),
            class_id=tuple(r.hypothesis.class_id for _, r in results),
            score=np.array([r.hypothesis.score for _, r in results], dtype=float),
            pose=np.array([pose7(r.pose.pose) for _, r in results], dtype=float).reshape(-1, 7),
            covariance=np.array([np.asarray(r.pose.covariance, dtype=float).reshape(36) for _, r in results],
                                dtype=float).reshape(-1, 36),
        )


def same_layout(store, reference) -> bool:
    """Whether typestore ``store`` (a bag's) defines every type of :data:`LAYOUT_TYPES` as
    ``reference`` (fgslam's) does: the parser's precondition."""
    try:
        return all(store.fielddefs[t] == reference.fielddefs[t] for t in LAYOUT_TYPES)
    except (KeyError, AttributeError):
        return False


class _Unreadable(Exception):
    """The bytes are not a Detection3DArray the parser reads (the caller falls back)."""


_U32 = struct.Struct("<I").unpack_from
_STAMP = struct.Struct("<iI").unpack_from


def _string(buf: bytes, pos: int) -> tuple[str, int]:
    """The string at ``pos`` (aligned to 4 first) and the position after it."""
    pos = (pos + 3) & ~3
    (length,) = _U32(buf, pos)
    end = pos + 4 + length
    if length == 0 or end > len(buf) or buf[end - 1]:  # no terminating NUL: rosbags refuses it
        raise _Unreadable
    return buf[pos + 4:end - 1].decode(), end


def _count(buf: bytes, pos: int, min_size: int) -> tuple[int, int]:
    """A sequence's element count at ``pos`` (aligned to 4 first), checked against the bytes left
    (each element takes at least ``min_size``), and the position after it."""
    pos = (pos + 3) & ~3
    (n,) = _U32(buf, pos)
    if n * min_size > len(buf) - pos - 4:
        raise _Unreadable
    return n, pos + 4


def parse_detection3d_array(raw: bytes | memoryview) -> Detections | None:
    """The :class:`Detections` of one Detection3DArray's CDR bytes (vision_msgs 4.x layout), or
    None when the bytes are not such a message in little-endian CDR (see module doc)."""
    if len(raw) < 4 or bytes(raw[:2]) != b"\x00\x01":
        return None
    buf = bytes(raw[4:])
    try:
        return _parse(buf)
    except (_Unreadable, struct.error, UnicodeDecodeError, IndexError):
        return None


def _parse(buf: bytes) -> Detections:
    sec, nanosec = _STAMP(buf, 0)
    frame_id, pos = _string(buf, 8)
    # a detection is at least a header (13), a count (4), a box (80) and an id (5)
    n, pos = _count(buf, pos, 102)
    det_frame, ids, box_at = [], [], []
    result_det, class_id, result_at = [], [], []
    for i in range(n):
        f, pos = _string(buf, ((pos + 3) & ~3) + 8)  # the detection's stamp, then its frame id
        det_frame.append(f)
        k, pos = _count(buf, pos, 5 + 8 * RESULT_F64)  # a class id (5) and the floats
        for _ in range(k):
            c, pos = _string(buf, pos)
            pos = (pos + 7) & ~7
            result_det.append(i)
            class_id.append(c)
            result_at.append(pos)
            pos += 8 * RESULT_F64
        pos = (pos + 7) & ~7
        box_at.append(pos)
        s, pos = _string(buf, pos + 8 * BBOX_F64)  # the box, then the id
        ids.append(s)
    if pos + 3 < len(buf):  # rosbags' own test: at most the padding to 4 after the last field
        raise _Unreadable
    f64 = np.frombuffer(buf, dtype="<f8", count=len(buf) // 8)

    def gather(at: list[int], width: int) -> np.ndarray:
        return np.asarray(f64[np.asarray(at, dtype=np.int64)[:, None] // 8 + np.arange(width)], dtype=float)

    res = gather(result_at, RESULT_F64)
    box = gather(box_at, BBOX_F64)
    return Detections(
        stamp_ns=sec * 1_000_000_000 + nanosec, frame_id=frame_id, det_frame=tuple(det_frame),
        center=box[:, :7], size=box[:, 7:], ids=tuple(ids), result_det=np.asarray(result_det, dtype=np.int64),
        class_id=tuple(class_id), score=res[:, 0], pose=res[:, 1:8], covariance=res[:, 8:],
    )


def _same_as_fgslam(store) -> bool:
    return same_layout(store, typestore())


# the rock and crater kinds' bag layers read their frames with it
DETECTIONS_PARSER = CdrParser(DETECTIONS_TYPE, parse_detection3d_array, _same_as_fgslam)

"""Vectorised CDR decoding of the fixed-layout motion messages (commands, IMU, odometry).

rosbags deserialises one message at a time in Python (~100 us each, most of a bag's read time on
a kilometre traverse with ~90 messages per second). The motion messages have a fixed layout once
their frame names are known: a header (stamp, frame_id string), for odometry a child frame
string, then a run of float64. A block of such messages with one byte length and one frame-name
length per string is one (n, L) byte array, and every field is a strided view of it.

Layout (ROS 2 XCDR1, little endian, as rosbag2 records it): a 4-byte encapsulation header
``00 01 00 00``; then, aligned relative to byte 4: ``int32 sec, uint32 nanosec, uint32 len,
len bytes`` (the frame_id with its NUL), padding to 8, the float64 fields. Anything else (big
endian, another encapsulation, a group with mixed string lengths) is left to the per-message
deserializer: :func:`decode_block` returns None.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"


@dataclass(frozen=True)
class Layout:
    """A message type as CDR: ``header`` (std_msgs/Header first), ``strings`` (further string
    fields before the floats), ``n_f64`` (the float64 run that follows)."""

    msgtype: str
    header: bool
    strings: int
    n_f64: int


LAYOUTS = {
    "geometry_msgs/msg/TwistStamped": Layout("geometry_msgs/msg/TwistStamped", True, 0, 6),
    "geometry_msgs/msg/Twist": Layout("geometry_msgs/msg/Twist", False, 0, 6),
    # orientation 4, its covariance 9, angular velocity 3 + 9, linear acceleration 3 + 9
    "sensor_msgs/msg/Imu": Layout("sensor_msgs/msg/Imu", True, 0, 37),
    # child_frame_id; pose (position 3, orientation 4) + covariance 36; twist 6 + covariance 36
    "nav_msgs/msg/Odometry": Layout("nav_msgs/msg/Odometry", True, 1, 85),
}

# float64 offsets of the fields the decoders use
IMU_QUAT, IMU_GYRO, IMU_ACCEL = slice(0, 4), slice(13, 16), slice(25, 28)
ODOM_POS, ODOM_QUAT, ODOM_V, ODOM_YAW_RATE = slice(0, 3), slice(3, 7), 43, 48
TWIST_V, TWIST_YAW_RATE = 0, 5


def _u32(block: np.ndarray, off: int) -> np.ndarray:
    return np.ascontiguousarray(block[:, off:off + 4]).view("<u4")[:, 0]


def _align(off: int, n: int) -> int:
    """``off`` (absolute, data starting at byte 4) rounded up to a multiple of ``n`` of the data."""
    return 4 + (-(-(off - 4) // n)) * n


@dataclass(frozen=True)
class Block:
    """Decoded messages: ``stamp_ns`` (n,) int64 from the header (None for unstamped types),
    ``f64`` (n, n_f64) the float run, ``frame_id`` of the header (one per block)."""

    stamp_ns: np.ndarray | None
    f64: np.ndarray
    frame_id: str


def decode_block(raws: list[bytes], layout: Layout) -> Block | None:
    """Decode messages of one type whose byte lengths and string lengths agree; None when they do
    not (or the encoding is not plain little-endian CDR): decode those one by one."""
    if not raws:
        return None
    n_len = len(raws[0])
    if any(len(r) != n_len for r in raws) or n_len < 4:
        return None
    block = np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), n_len)
    if not np.all(block[:, :4] == np.frombuffer(CDR_LE, np.uint8)):
        return None
    off, stamp, frame = 4, None, ""
    if layout.header:
        if n_len < 16:
            return None
        sec = np.ascontiguousarray(block[:, 4:8]).view("<i4")[:, 0].astype(np.int64)
        nsec = _u32(block, 8).astype(np.int64)
        stamp = sec * 1_000_000_000 + nsec
        flen = _u32(block, 12)
        if np.any(flen != flen[0]):
            return None
        off = 16 + int(flen[0])
        if off > n_len:
            return None
        frame = bytes(block[0, 16:off]).rstrip(b"\x00").decode("utf-8", "replace")
    for _ in range(layout.strings):
        off = _align(off, 4)
        if off + 4 > n_len:
            return None
        slen = _u32(block, off)
        if np.any(slen != slen[0]):
            return None
        off += 4 + int(slen[0])
    off = _align(off, 8)
    if off + 8 * layout.n_f64 != n_len:
        return None
    f64 = np.ascontiguousarray(block[:, off:]).view("<f8").reshape(len(raws), layout.n_f64)
    return Block(stamp, f64, frame)


def _seconds(ns: np.ndarray) -> np.ndarray:
    """Integer ns -> float s, as ``ns / 1e9`` of a Python int (the per-message decoders' rule)."""
    return np.array([n / 1e9 for n in ns.tolist()])


def batch_cmd_vel(block: Block, log_ns: list[int]) -> tuple[np.ndarray, list]:
    """Stamps (ns) and CmdVel (or the error of an invalid row) of TwistStamped (header stamp) or
    Twist (log time) messages."""
    from reloc.measurements import CmdVel, batch_planar

    ns = block.stamp_ns if block.stamp_ns is not None else np.asarray(log_ns, np.int64)
    return ns, batch_planar(CmdVel, _seconds(ns), block.f64[:, TWIST_V], block.f64[:, TWIST_YAW_RATE])


def batch_imu(block: Block, log_ns: list[int]) -> tuple[np.ndarray, list]:
    """Stamps and ImuSample of sensor_msgs/Imu messages (orientation xyzw, gyro, specific force)."""
    from reloc.measurements import batch_imu as build

    f = block.f64
    return block.stamp_ns, build(_seconds(block.stamp_ns), f[:, IMU_QUAT], f[:, IMU_GYRO], f[:, IMU_ACCEL])


def batch_wheel_odom(block: Block, log_ns: list[int]) -> tuple[np.ndarray, list]:
    """Stamps and WheelOdometry of nav_msgs/Odometry (twist: body x speed, z yaw rate)."""
    from reloc.measurements import WheelOdometry, batch_planar

    return block.stamp_ns, batch_planar(WheelOdometry, _seconds(block.stamp_ns), block.f64[:, ODOM_V],
                                        block.f64[:, ODOM_YAW_RATE])


def batch_ground_truth(block: Block, log_ns: list[int]) -> tuple[np.ndarray, list]:
    """Stamps and GroundTruthPose of nav_msgs/Odometry (pose of the child frame in the header frame)."""
    from reloc.measurements import batch_ground_truth as build

    f = block.f64
    return block.stamp_ns, build(_seconds(block.stamp_ns), f[:, ODOM_POS], f[:, ODOM_QUAT])


def row_finite(block: Block) -> np.ndarray:
    """(n,) whether every float of each message is finite (the batch form of ``has_nonfinite``)."""
    return np.all(np.isfinite(block.f64), axis=1)

"""Deserialized ROS 2 messages -> fgslam measurements: the motion inputs and ground truth (one
function per message type), and the reader's settings. Landmark messages are decoded by their
kind's codec (:mod:`reloc.kinds`, :class:`reloc.bag_spec.BagCodec`; rocks: :mod:`reloc.rock_bag`).

Each decoder takes the message object (as rosbags deserializes it) and the stamp in integer
nanoseconds, and returns a measurement or raises :class:`~reloc.errors.MeasurementError` (NaN,
non-unit quaternion, bad covariance) or :class:`~reloc.bag_spec.MessageContentError` (content
that cannot be a measurement). The bag reader turns both into counted repairs or a
:class:`BagError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fgslam.errors import BagError
from reloc.bag_spec import stamp_s
from reloc.measurements import CmdVel, GroundTruthPose, ImuSample, WheelOdometry


@dataclass(frozen=True)
class BagReaderConfig:
    """How the reader interprets message content.

    ``base_frame``: the frame name meaning base_link. ``default_rock_sigma_m``: isotropic 1-sigma
    position noise for detections without a usable covariance (bags of other tools often leave it
    zero); None makes such a detection invalid. ``rock_class_ids``: hypotheses counted as rocks
    (None: any class; the best-scoring hypothesis gives the score). Every landmark kind's decoder
    receives this config (:class:`reloc.bag_spec.DecodeContext`). ``reorder_window_s``: how far
    (s of stamp) a message may arrive after later-stamped ones and still be put in order (the
    reader holds that much stream in memory; later ones are dropped as late).
    """

    base_frame: str = "base_link"
    default_rock_sigma_m: float | None = None
    rock_class_ids: tuple[str, ...] | None = None
    reorder_window_s: float = 30.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.reorder_window_s) and self.reorder_window_s >= 0):
            raise BagError(f"bag reader reorder_window_s must be finite and >= 0, got {self.reorder_window_s}")


def header_ns(header) -> int:
    """std_msgs/Header stamp -> integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _quat_xyzw(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def decode_cmd_vel(msg, ns: int) -> CmdVel:
    """TwistStamped or Twist -> CmdVel (base_link x speed m/s, z yaw rate rad/s)."""
    twist = getattr(msg, "twist", msg)
    return CmdVel(stamp_s(ns), twist.linear.x, twist.angular.z)


def decode_imu(msg, ns: int) -> ImuSample:
    """sensor_msgs/Imu -> ImuSample (orientation xyzw, gyro rad/s, specific force m/s^2)."""
    return ImuSample(
        stamp_s(ns),
        _quat_xyzw(msg.orientation),
        _xyz(msg.angular_velocity),
        _xyz(msg.linear_acceleration),
    )


def decode_wheel_odom(msg, ns: int) -> WheelOdometry:
    """nav_msgs/Odometry -> WheelOdometry (twist: body x speed, z yaw rate)."""
    return WheelOdometry(stamp_s(ns), msg.twist.twist.linear.x, msg.twist.twist.angular.z)


def decode_ground_truth(msg, ns: int) -> GroundTruthPose:
    """nav_msgs/Odometry -> GroundTruthPose (pose of child frame in header frame)."""
    p = msg.pose.pose
    return GroundTruthPose(stamp_s(ns), _xyz(p.position), _quat_xyzw(p.orientation))


def has_nonfinite(msg) -> bool:
    """True when any float field of a deserialized message (recursively) is NaN or inf."""
    if isinstance(msg, float):
        return not np.isfinite(msg)
    if isinstance(msg, np.ndarray):
        return msg.dtype.kind == "f" and not np.all(np.isfinite(msg))
    if isinstance(msg, (list, tuple)):
        return any(has_nonfinite(v) for v in msg)
    fields = getattr(msg, "__dataclass_fields__", None)
    if fields:
        return any(has_nonfinite(getattr(msg, name)) for name in fields if name != "__msgtype__")
    return False


def same_measurement(a, b) -> bool:
    """True when two measurements have the same type and identical field values (NaN-free)."""
    if type(a) is not type(b):
        return False
    for name in a.__slots__:
        va, vb = getattr(a, name), getattr(b, name)
        if isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
            if not np.array_equal(va, vb):
                return False
        elif va != vb:
            return False
    return True

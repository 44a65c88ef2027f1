"""Deserialized ROS 2 messages -> fgslam measurements (one function per message type).

Each decoder takes the message object (as rosbags deserializes it) and the stamp in integer
nanoseconds, and returns a measurement or raises :class:`~reloc.errors.MeasurementError` (NaN,
non-unit quaternion, bad covariance) or :class:`DecodeError` (content that cannot be a
measurement). The bag reader turns both into counted repairs or a :class:`BagError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fgslam.errors import BagError
from reloc.measurements import CmdVel, GroundTruthPose, ImuSample, RockObservations, WheelOdometry


class DecodeError(BagError):
    """One message holds content that cannot become a measurement (bad shape, bad covariance)."""


class UnknownFrameError(BagError):
    """Rock detections are in a frame with no known transform to base_link."""


@dataclass(frozen=True)
class BagReaderConfig:
    """How the reader interprets message content.

    ``base_frame``: the frame name meaning base_link. ``default_rock_sigma_m``: isotropic 1-sigma
    position noise for detections without a usable covariance (bags of other tools often leave it
    zero); None makes such a detection invalid. ``rock_class_ids``: hypotheses counted as rocks
    (None: any class; the best-scoring hypothesis gives the score). ``reorder_window_s``: how far
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


def _t(ns: int) -> float:
    return ns / 1e9


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _quat_xyzw(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def decode_cmd_vel(msg, ns: int) -> CmdVel:
    """TwistStamped or Twist -> CmdVel (base_link x speed m/s, z yaw rate rad/s)."""
    twist = getattr(msg, "twist", msg)
    return CmdVel(_t(ns), twist.linear.x, twist.angular.z)


def decode_imu(msg, ns: int) -> ImuSample:
    """sensor_msgs/Imu -> ImuSample (orientation xyzw, gyro rad/s, specific force m/s^2)."""
    return ImuSample(
        _t(ns),
        _quat_xyzw(msg.orientation),
        _xyz(msg.angular_velocity),
        _xyz(msg.linear_acceleration),
    )


def decode_wheel_odom(msg, ns: int) -> WheelOdometry:
    """nav_msgs/Odometry -> WheelOdometry (twist: body x speed, z yaw rate)."""
    return WheelOdometry(_t(ns), msg.twist.twist.linear.x, msg.twist.twist.angular.z)


def decode_ground_truth(msg, ns: int) -> GroundTruthPose:
    """nav_msgs/Odometry -> GroundTruthPose (pose of child frame in header frame)."""
    p = msg.pose.pose
    return GroundTruthPose(_t(ns), _xyz(p.position), _quat_xyzw(p.orientation))


class RockDecoder:
    """vision_msgs/Detection3DArray -> RockObservations in base_link.

    ``T_base_frame`` maps a detection frame name to a (4, 4) transform into base_link; the base
    frame itself is the identity. Position = ``bbox.center.position``; diameter = the largest
    ``bbox.size`` extent; score and 3x3 position covariance from the best rock hypothesis.
    """

    def __init__(self, config: BagReaderConfig, T_base_frame: dict[str, np.ndarray] | None) -> None:
        self.config = config
        self.T_base_frame: dict[str, np.ndarray] = {config.base_frame: np.eye(4)}
        for name, T in (T_base_frame or {}).items():
            T = np.asarray(T, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise BagError(
                    f"camera_frames[{name!r}] must be a finite (4, 4) transform, got {T.shape}"
                )
            R = T[:3, :3]
            if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
                raise BagError(f"camera_frames[{name!r}] rotation block is not a rotation matrix")
            if name == config.base_frame and not np.allclose(T, np.eye(4)):
                raise BagError(f"camera_frames[{name!r}] redefines the base frame")
            self.T_base_frame[name] = T

    def _hypothesis(self, det):
        rocks = [
            r
            for r in det.results
            if self.config.rock_class_ids is None
            or r.hypothesis.class_id in self.config.rock_class_ids
        ]
        return max(rocks, key=lambda r: r.hypothesis.score) if rocks else None

    def _covs(self, cov6: np.ndarray, has_cov: np.ndarray) -> np.ndarray:
        """(N, 3, 3) position covariances from (N, 6, 6) pose covariances, or the default."""
        cov = cov6[:, :3, :3].copy()
        finite = np.all(np.isfinite(cov), axis=(1, 2))
        usable = has_cov & finite
        if np.any(usable):
            c = cov[usable]
            sym = np.all(np.abs(c - np.swapaxes(c, 1, 2)) <= 1e-12 * (1.0 + np.abs(c)), axis=(1, 2))
            pd = np.zeros(len(c), dtype=bool)
            pd[sym] = np.linalg.eigvalsh(c[sym])[:, 0] > 0.0
            usable[np.flatnonzero(usable)[~pd]] = False
        bad = ~usable & finite  # NaN covariances stay: RockObservations reports them as NaN
        if np.any(bad):
            if self.config.default_rock_sigma_m is None:
                raise DecodeError(
                    f"{int(bad.sum())} detection(s) have no positive-definite position "
                    "covariance (set BagReaderConfig.default_rock_sigma_m to supply one)"
                )
            cov[bad] = np.eye(3) * self.config.default_rock_sigma_m**2
        return cov

    def __call__(self, msg, ns: int) -> RockObservations:
        """Decode one frame (detections holding only non-rock classes are skipped)."""
        n = len(msg.detections)
        xyz = np.empty((n, 3))
        cov6 = np.zeros((n, 6, 6))
        has_cov = np.zeros(n, dtype=bool)
        size = np.empty(n)
        score = np.ones(n)
        R_t = np.empty((n, 3, 4))
        keep = np.ones(n, dtype=bool)
        for i, det in enumerate(msg.detections):
            result = self._hypothesis(det)
            if result is None and det.results:
                keep[i] = False  # only other classes
                continue
            frame = det.header.frame_id or msg.header.frame_id or self.config.base_frame
            T = self.T_base_frame.get(frame)
            if T is None:
                raise UnknownFrameError(
                    f"rock detections in frame {frame!r}, which has no transform to "
                    f"{self.config.base_frame!r}; pass camera_frames={{{frame!r}: T_base_{frame}}}"
                )
            R_t[i] = T[:3]
            c, b = det.bbox.center.position, det.bbox.size
            xyz[i] = (c.x, c.y, c.z)
            size[i] = max(b.x, b.y, b.z)
            if result is not None:
                cov6[i] = np.reshape(result.pose.covariance, (6, 6))
                has_cov[i] = True
                score[i] = result.hypothesis.score
        xyz, cov6, has_cov, size, score, R_t = (
            a[keep] for a in (xyz, cov6, has_cov, size, score, R_t)
        )
        R, t = R_t[:, :, :3], R_t[:, :, 3]
        cov = self._covs(cov6, has_cov)
        return RockObservations(
            _t(ns),
            np.einsum("nij,nj->ni", R, xyz) + t,
            R @ cov @ np.swapaxes(R, 1, 2),
            size,
            score,
        )


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

"""Write a measurement stream as a ROS 2 bag (rosbag2 directory, MCAP storage, zstd chunks).

Topics and types are those of DESIGN.md (``reloc.bag_spec``): CmdVel -> geometry_msgs/TwistStamped,
ImuSample -> sensor_msgs/Imu, WheelOdometry and GroundTruthPose -> nav_msgs/Odometry, and each
registered landmark kind's observation through its codec (``reloc.kinds``; rocks ->
vision_msgs/Detection3DArray, ``reloc.rock_bag``). Header stamps and MCAP log
times are the measurement time in integer nanoseconds. Messages are written in the order given,
so a caller can also write a recording as it was received.

Compression: rosbags' ``CompressionMode.STORAGE`` on the MCAP plugin zstd-compresses every MCAP
chunk (about 1 MiB uncompressed each), which is what ``ros2 bag record --storage mcap
--storage-preset-profile zstd_fast`` produces; ``metadata.yaml`` then lists no file/message
compression, as for ros2's own storage-level compression.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

from reloc.bag_spec import (
    CMD_VEL_TYPE,
    IMU_TYPE,
    ODOMETRY_TYPE,
    ROCK_CLASS_ID,
    ROCKS_TYPE,
    WORLD_FRAME,
    BagEncoding,
    TopicNames,
    typestore,
)
from reloc.kinds import kinds_with
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    Measurement,
    RockObservations,
    WheelOdometry,
)
from sim.errors import SimError

log = logging.getLogger(__name__)

ROSBAG2_VERSION = 8  # the metadata version ROS 2 Jazzy writes


class BagWriteError(SimError):
    """A bag could not be written (target exists, bad measurement, I/O failure)."""


@dataclass(frozen=True)
class BagSummary:
    """What :func:`write_bag` wrote: ``counts`` per topic, ``n_bytes`` on disk, stamps (s)."""

    path: Path
    counts: dict[str, int] = field(default_factory=dict)
    n_bytes: int = 0
    t_start: float = float("nan")
    t_end: float = float("nan")

    @property
    def n_messages(self) -> int:
        return sum(self.counts.values())


def stamp_ns(t: float) -> int:
    """Seconds (float) -> integer nanoseconds, rounded to the nearest ns."""
    return round(float(t) * 1e9)


class _Encoder:
    """Builds rosbags message objects from measurements (one instance per bag)."""

    def __init__(self, frame_id_base: str, encoding: BagEncoding) -> None:
        self.ts = typestore()
        self.types = self.ts.types
        self.frame_base = frame_id_base
        self.enc = encoding
        e = encoding
        self.imu_orientation_cov = np.diag(np.square(e.imu_orientation_sigma_rad)).ravel()
        self.imu_gyro_cov = (np.eye(3) * e.imu_gyro_sigma_radps**2).ravel()
        self.imu_accel_cov = (np.eye(3) * e.imu_accel_sigma_mps2**2).ravel()
        self.wheel_pose_cov = (np.eye(6) * e.unknown_var).ravel()
        twist_var = np.full(6, e.unknown_var)
        twist_var[0], twist_var[5] = e.wheel_v_sigma_mps**2, e.wheel_yaw_rate_sigma_radps**2
        self.wheel_twist_cov = np.diag(twist_var).ravel()

    # -- small builders ---------------------------------------------------------------------
    def header(self, ns: int, frame_id: str):
        T = self.types
        sec, nanosec = divmod(ns, 1_000_000_000)
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def vec3(self, v):
        return self.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v):
        return self.types["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, q):
        return self.types["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        )

    def twist(self, v_mps: float, yaw_rate_radps: float):
        return self.types["geometry_msgs/msg/Twist"](
            linear=self.vec3((v_mps, 0.0, 0.0)), angular=self.vec3((0.0, 0.0, yaw_rate_radps))
        )

    def pose(self, p, q):
        return self.types["geometry_msgs/msg/Pose"](
            position=self.point(p), orientation=self.quat(q)
        )

    def odometry(self, ns: int, frame_id: str, pose, pose_cov, twist, twist_cov):
        T = self.types
        return T[ODOMETRY_TYPE](
            header=self.header(ns, frame_id),
            child_frame_id=self.frame_base,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=pose_cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov),
        )

    # -- one builder per measurement type ---------------------------------------------------
    def cmd_vel(self, m: CmdVel, ns: int):
        return self.types[CMD_VEL_TYPE](
            header=self.header(ns, self.frame_base), twist=self.twist(m.v_mps, m.yaw_rate_radps)
        )

    def imu(self, m: ImuSample, ns: int):
        return self.types[IMU_TYPE](
            header=self.header(ns, self.frame_base),
            orientation=self.quat(m.quat_xyzw),
            orientation_covariance=self.imu_orientation_cov.copy(),
            angular_velocity=self.vec3(m.gyro_radps),
            angular_velocity_covariance=self.imu_gyro_cov.copy(),
            linear_acceleration=self.vec3(m.accel_mps2),
            linear_acceleration_covariance=self.imu_accel_cov.copy(),
        )

    def wheel(self, m: WheelOdometry, ns: int):
        # Wheel odometry reports body rates only; its (unmeasured) pose carries "unknown" variance.
        pose = self.pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        return self.odometry(
            ns,
            "odom",
            pose,
            self.wheel_pose_cov.copy(),
            self.twist(m.v_mps, m.yaw_rate_radps),
            self.wheel_twist_cov.copy(),
        )

    def ground_truth(self, m: GroundTruthPose, ns: int):
        return self.odometry(
            ns,
            WORLD_FRAME,
            self.pose(m.position_m, m.quat_xyzw),
            np.zeros(36),
            self.twist(0.0, 0.0),
            np.zeros(36),
        )


def _fast_encoder(enc: _Encoder, encoding: BagEncoding):
    """The precompiled encoders of :mod:`sim.bag_fast` when they reproduce rosbags' bytes on
    sample messages of every type (else None: the rosbags path is used)."""
    from sim.bag_fast import FastEncoder, check_against_rosbags

    fast = FastEncoder(enc.frame_base, WORLD_FRAME, ROCK_CLASS_ID,
                       (enc.imu_orientation_cov, enc.imu_gyro_cov, enc.imu_accel_cov),
                       (enc.wheel_pose_cov, enc.wheel_twist_cov), encoding.rock_rotation_var)
    rng = np.random.default_rng(0)
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    from reloc.rock_bag import encode_rocks

    samples = [
        (CmdVel(1.25, 0.11, -0.02), 1_250_000_000, "cmd_vel", enc.cmd_vel, CMD_VEL_TYPE),
        (ImuSample(2.5, q, rng.standard_normal(3), rng.standard_normal(3)), 2_500_000_001, "imu", enc.imu, IMU_TYPE),
        (WheelOdometry(3.0, 0.1, 0.01), 3_000_000_000, "wheel", enc.wheel, ODOMETRY_TYPE),
        (GroundTruthPose(4.0, rng.standard_normal(3), q), 4_000_000_000, "ground_truth", enc.ground_truth, ODOMETRY_TYPE),
    ]
    for n in range(4):
        a = rng.standard_normal((n, 3, 3))
        samples.append((RockObservations(5.0 + n, rng.standard_normal((n, 3)), a @ np.swapaxes(a, 1, 2) + np.eye(3),
                                         rng.random(n) + 0.1, rng.random(n)), 5_000_000_000 + n, "rocks",
                        lambda m, ns: encode_rocks(m, ns, enc), ROCKS_TYPE))
    if check_against_rosbags(fast, enc, samples):
        return fast
    log.warning("fast CDR encoders disagree with rosbags on sample messages; using rosbags")
    return None


def _remove_bag_dir(path: Path) -> None:
    """Delete an existing bag directory, refusing anything that does not look like one."""
    if not path.is_dir():
        raise BagWriteError(f"bag path {path} exists and is not a directory; not overwriting")
    allowed = {".mcap", ".db3", ".yaml", ".zstd"}
    strangers = [p.name for p in path.iterdir() if p.is_dir() or p.suffix not in allowed]
    if strangers:
        raise BagWriteError(
            f"bag path {path} holds non-bag entries {strangers[:5]}; refusing to overwrite it"
        )
    shutil.rmtree(path)


def write_bag(
    path: Path,
    measurements: Iterable[Measurement],
    *,
    topics: TopicNames | None = None,
    frame_id_base: str = "base_link",
    overwrite: bool = False,
    encoding: BagEncoding | None = None,
) -> BagSummary:
    """Write ``measurements`` (any order; written as given) to the rosbag2 directory ``path``.

    Times are seconds (>= 0) and become integer-ns header stamps and log times. Rock positions
    and covariances stay in ``frame_id_base``. Raises :class:`BagWriteError` when ``path`` exists
    (unless ``overwrite``), on an unknown measurement type or a negative time; a partly written
    bag is removed.
    """
    path = Path(path)
    topics = topics or TopicNames()
    encoding = encoding or BagEncoding()
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagWriteError(f"bag path {path} exists; pass overwrite=True to replace it")
        _remove_bag_dir(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    enc = _Encoder(frame_id_base, encoding)
    fast = _fast_encoder(enc, encoding)
    routes = {
        CmdVel: (topics.cmd_vel, CMD_VEL_TYPE, enc.cmd_vel),
        ImuSample: (topics.imu, IMU_TYPE, enc.imu),
        WheelOdometry: (topics.wheel_odom, ODOMETRY_TYPE, enc.wheel),
        GroundTruthPose: (topics.ground_truth, ODOMETRY_TYPE, enc.ground_truth),
    }
    for kind in kinds_with("bag"):  # landmark observations through their kind's codec
        codec = kind.layer("bag")
        routes[kind.measurement_type] = (
            topics.topic_of(kind.name, codec), codec.msgtypes[0],
            lambda m, ns, encode=codec.encode: encode(m, ns, enc),
        )
    encode = {t: (lambda m, ns, b=b, mt=mt: enc.ts.serialize_cdr(b(m, ns), mt)) for t, (_, mt, b) in routes.items()}
    if fast is not None:  # byte-identical CDR written directly (checked against rosbags at start)
        encode.update({CmdVel: fast.cmd_vel, ImuSample: fast.imu, WheelOdometry: fast.wheel,
                       GroundTruthPose: fast.ground_truth, RockObservations: fast.rocks})
    counts: dict[str, int] = {}
    connections = {}
    ns_min, ns_max = None, None
    writer = Writer(path, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    try:
        with writer:
            for m in measurements:
                route = routes.get(type(m))
                if route is None:
                    raise BagWriteError(
                        f"cannot write {type(m).__name__} to bag {path}: unknown type (neither a motion input, "
                        "ground truth nor the observation of a registered landmark kind with a bag layer)"
                    )
                topic, msgtype, _ = route
                ns = stamp_ns(m.t)
                if ns < 0:
                    raise BagWriteError(
                        f"cannot write {type(m).__name__} at t={m.t} s to {path}: negative time"
                    )
                conn = connections.get(topic)
                if conn is None:
                    conn = writer.add_connection(topic, msgtype, typestore=enc.ts)
                    connections[topic] = conn
                    counts[topic] = 0
                writer.write(conn, ns, encode[type(m)](m, ns))
                counts[topic] += 1
                ns_min = ns if ns_min is None else min(ns_min, ns)
                ns_max = ns if ns_max is None else max(ns_max, ns)
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise
    n_bytes = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    log.info("wrote bag %s: %s, %.1f kB", path, counts, n_bytes / 1e3)
    return BagSummary(
        path=path,
        counts=counts,
        n_bytes=n_bytes,
        t_start=float("nan") if ns_min is None else ns_min / 1e9,
        t_end=float("nan") if ns_max is None else ns_max / 1e9,
    )

"""Write a measurement stream as a ROS 2 bag (rosbag2 directory, MCAP storage, zstd chunks).

Topics and types are those of DESIGN.md (``reloc.bag_spec``): CmdVel -> geometry_msgs/TwistStamped,
ImuSample -> sensor_msgs/Imu, WheelOdometry and GroundTruthPose -> nav_msgs/Odometry, and each
registered landmark kind's observation through its codec (``reloc.kinds``; rocks ->
vision_msgs/Detection3DArray, ``reloc.rock_bag``). Header stamps and MCAP log
times are the measurement time in integer nanoseconds. Messages are written in the order given,
so a caller can also write a recording as it was received.

Around the measurements, :mod:`sim.bag_scene` adds what a rover's recording holds: stereo images
(:class:`reloc.camera_bag.StereoFrame` records in the stream) with their CameraInfo, ``/tf`` and
``/tf_static``, the orbital catalog as latched markers (and its file named in the bag's
``metadata.yaml`` custom data), with a configurable start epoch and command style
(:class:`sim.bag_scene.BagStyle`).

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
    BASE_FRAME,
    CAMERA_INFO_TYPE,
    CMD_VEL_TYPE,
    CMD_VEL_UNSTAMPED_TYPE,
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    MARKERS_TYPE,
    ODOMETRY_TYPE,
    ROCK_CLASS_ID,
    ROCKS_TYPE,
    TF_TYPE,
    WORLD_FRAME,
    BagEncoding,
    TopicNames,
    typestore,
)
from reloc.camera_bag import (
    StereoFrame,
    camera_info_message,
    catalog_markers,
    image_message,
    tf_message,
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
from sim.bag_scene import BagScene, BagStyle, latched_qos
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


def message_builder(frame_id_base: str = "base_link", encoding: BagEncoding | None = None) -> _Encoder:
    """The writer's message builder (:class:`reloc.bag_spec.MessageBuilder`, with ``ts`` its
    typestore), for a caller that writes a landmark kind's messages into a bag of its own."""
    return _Encoder(frame_id_base, encoding or BagEncoding())


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


class _Out:
    """The writer's topics: connections made on first use, messages counted, stamps tracked."""

    def __init__(self, writer, ts) -> None:
        self.writer, self.ts = writer, ts
        self.connections: dict = {}
        self.counts: dict[str, int] = {}
        self.ns_min = self.ns_max = None

    def put(self, topic: str, msgtype: str, ns: int, data: bytes, latched: bool = False) -> None:
        conn = self.connections.get(topic)
        if conn is None:
            conn = self.writer.add_connection(topic, msgtype, typestore=self.ts,
                                              offered_qos_profiles=latched_qos() if latched else ())
            self.connections[topic] = conn
            self.counts[topic] = 0
        self.writer.write(conn, ns, data)
        self.counts[topic] += 1
        self.ns_min = ns if self.ns_min is None else min(self.ns_min, ns)
        self.ns_max = ns if self.ns_max is None else max(self.ns_max, ns)

    def msg(self, topic: str, msgtype: str, ns: int, message, latched: bool = False) -> None:
        self.put(topic, msgtype, ns, self.ts.serialize_cdr(message, msgtype), latched)


def _scene_writers(out: _Out, enc: _Encoder, topics: TopicNames, style: BagStyle, scene: BagScene | None):
    """(at_start(ns), frame(StereoFrame, ns), truth(GroundTruthPose, ns)) of the scene (see module doc)."""
    scene = scene or BagScene()
    img_type = IMAGE_TYPE if style.image_format == "raw" else COMPRESSED_IMAGE_TYPE
    suffix = "" if style.image_format == "raw" else "/compressed"

    def at_start(ns: int) -> None:
        if style.tf and scene.static_transforms():
            out.msg(topics.tf_static, TF_TYPE, ns, tf_message(enc, ns, scene.static_transforms()), latched=True)
        if style.tf and scene.catalog_xy_m is not None:
            out.msg(topics.catalog, MARKERS_TYPE, ns,
                    catalog_markers(enc, ns, WORLD_FRAME, scene.catalog_xy_m, scene.catalog_size_m), latched=True)

    def frame(m: StereoFrame, ns: int) -> None:
        if scene.left is None or scene.right is None:
            raise BagWriteError("stereo images need the cameras' calibration: pass scene=BagScene(left=..., right=...)")
        for img, cal, image_topic, info_topic in ((m.left, scene.left, topics.left_image, topics.left_info),
                                                  (m.right, scene.right, topics.right_image, topics.right_info)):
            out.msg(image_topic + suffix, img_type, ns, image_message(enc, ns, cal.frame_id, img, style.image_format))
            out.msg(info_topic, CAMERA_INFO_TYPE, ns, camera_info_message(enc, ns, cal))

    def truth(m: GroundTruthPose, ns: int) -> None:
        if style.tf:
            out.msg(topics.tf, TF_TYPE, ns, tf_message(enc, ns, [(WORLD_FRAME, BASE_FRAME, (m.position_m, m.quat_xyzw))]))

    return at_start, frame, truth


def write_bag(
    path: Path,
    measurements: Iterable[Measurement],
    *,
    topics: TopicNames | None = None,
    frame_id_base: str = "base_link",
    overwrite: bool = False,
    encoding: BagEncoding | None = None,
    style: BagStyle | None = None,
    scene: BagScene | None = None,
    custom_data: dict[str, str] | None = None,
) -> BagSummary:
    """Write ``measurements`` (any order; written as given) to the rosbag2 directory ``path``.

    Times are seconds (>= 0) and become integer-ns header stamps and log times, offset by
    ``style.epoch_ns``. Rock positions and covariances stay in ``frame_id_base``.
    :class:`~reloc.camera_bag.StereoFrame` records become the stereo image and CameraInfo topics
    of ``scene``; ``custom_data`` goes into ``metadata.yaml`` (e.g. the catalog file's name).
    Raises :class:`BagWriteError` when ``path`` exists (unless ``overwrite``), on an unknown
    measurement type or a negative time; a partly written bag is removed.
    """
    path = Path(path)
    topics = topics or TopicNames()
    encoding = encoding or BagEncoding()
    style = style or BagStyle()
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagWriteError(f"bag path {path} exists; pass overwrite=True to replace it")
        _remove_bag_dir(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    enc = _Encoder(frame_id_base, encoding)
    fast = _fast_encoder(enc, encoding)
    cmd_type = CMD_VEL_TYPE if style.cmd_vel_stamped else CMD_VEL_UNSTAMPED_TYPE
    cmd_build = enc.cmd_vel if style.cmd_vel_stamped else (lambda m, ns: enc.twist(m.v_mps, m.yaw_rate_radps))
    routes = {
        CmdVel: (topics.cmd_vel, cmd_type, cmd_build),
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
        encode.update({ImuSample: fast.imu, WheelOdometry: fast.wheel,
                       GroundTruthPose: fast.ground_truth, RockObservations: fast.rocks})
        if style.cmd_vel_stamped:
            encode[CmdVel] = fast.cmd_vel
    writer = Writer(path, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    for key, value in (custom_data or {}).items():
        writer.set_custom_data(key, str(value))
    out = _Out(writer, enc.ts)
    at_start, frame, truth = _scene_writers(out, enc, topics, style, scene)
    try:
        with writer:
            started = False
            for m in measurements:
                route = routes.get(type(m))
                if route is None and not isinstance(m, StereoFrame):
                    raise BagWriteError(
                        f"cannot write {type(m).__name__} to bag {path}: unknown type (neither a motion input, "
                        "ground truth, a stereo frame nor the observation of a registered landmark kind with a "
                        "bag layer)"
                    )
                ns = stamp_ns(m.t)
                if ns < 0:
                    raise BagWriteError(
                        f"cannot write {type(m).__name__} at t={m.t} s to {path}: negative time"
                    )
                ns += style.epoch_ns
                if not started:
                    at_start(ns)
                    started = True
                if isinstance(m, StereoFrame):
                    frame(m, ns)
                    continue
                out.put(route[0], route[1], ns, encode[type(m)](m, ns))
                if isinstance(m, GroundTruthPose):
                    truth(m, ns)
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise
    n_bytes = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    log.info("wrote bag %s: %s, %.1f kB", path, out.counts, n_bytes / 1e3)
    return BagSummary(
        path=path,
        counts=out.counts,
        n_bytes=n_bytes,
        t_start=float("nan") if out.ns_min is None else out.ns_min / 1e9,
        t_end=float("nan") if out.ns_max is None else out.ns_max / 1e9,
    )

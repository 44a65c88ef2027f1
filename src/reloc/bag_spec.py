"""The bag spec of fgslam: topic names, message types, vision_msgs, and the codec seam of the
landmark kinds. The simulator's writer (``sim.bag_writer``) and the reader (``fgslam.io``) both
import it, so a recording and a reading agree by construction.

vision_msgs is not part of the rosbags Jazzy typestore, so its definitions are registered here
from the .msg text of the ROS 2 Jazzy release (vision_msgs 4.x). Bags embed their schemas, so
only writers (and readers of old bags without embedded definitions) need :func:`typestore`.

Motion inputs and ground truth have fixed topics (:class:`TopicNames`); each landmark kind brings
a :class:`BagCodec` (its topic, message types, decoder and encoder, see :mod:`reloc.kinds`). A
kind's topic is ``TopicNames.rocks`` for rocks, else ``TopicNames.kinds[name]`` or the codec's
default.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from reloc.errors import ConfigError, RelocError

# vision_msgs 4.x (ROS 2 Humble/Jazzy) field lists; comments of the upstream files dropped.
VISION_MSGS: dict[str, str] = {
    "vision_msgs/msg/ObjectHypothesis": """
string class_id
float64 score
""",
    "vision_msgs/msg/ObjectHypothesisWithPose": """
vision_msgs/ObjectHypothesis hypothesis
geometry_msgs/PoseWithCovariance pose
""",
    "vision_msgs/msg/BoundingBox3D": """
geometry_msgs/Pose center
geometry_msgs/Vector3 size
""",
    "vision_msgs/msg/Detection3D": """
std_msgs/Header header
vision_msgs/ObjectHypothesisWithPose[] results
vision_msgs/BoundingBox3D bbox
string id
""",
    "vision_msgs/msg/Detection3DArray": """
std_msgs/Header header
vision_msgs/Detection3D[] detections
""",
}

CMD_VEL_TYPE = "geometry_msgs/msg/TwistStamped"
CMD_VEL_UNSTAMPED_TYPE = "geometry_msgs/msg/Twist"  # read only: stamped by the bag's log time
IMU_TYPE = "sensor_msgs/msg/Imu"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
ROCKS_TYPE = "vision_msgs/msg/Detection3DArray"
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"


def ros2_msgtype(name: str) -> str:
    """The ROS 2 form of a message type name, the form of the types above and of the typestore:
    ``pkg/Type`` (the ROS 1 form, which rosbag2 accepts and some recorders write, e.g.
    ``sensor_msgs/Image``) -> ``pkg/msg/Type``; any other name is returned unchanged. Every type
    check and every deserialisation of a bag's messages goes through it."""
    pkg, sep, typ = name.partition("/")
    if sep and pkg and typ and "/" not in typ:
        return f"{pkg}/msg/{typ}"
    return name

ROCK_CLASS_ID = "rock"
WORLD_FRAME = "world"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
LEFT_CAMERA_FRAME = "stereo_left_optical"  # the rectified left camera (z forward, x right, y down)
RIGHT_CAMERA_FRAME = "stereo_right_optical"


@dataclass(frozen=True)
class TopicNames:
    """Topic names of a bag, one per input role. Required on read: ``imu``, one of ``cmd_vel`` /
    ``wheel_odom``, and the topic of at least one landmark kind (``rocks``), or the stereo image
    topics for the image front-end (``left_image``, ``right_image``, ``left_info``,
    ``right_info``, mounting from ``tf_static``); ``ground_truth`` is optional. ``kinds`` maps
    another kind's name to its topic (default: its codec's ``default_topic``). ``tf`` and
    ``catalog`` are written for viewers (the rover's frames, the orbital catalog as markers)."""

    cmd_vel: str = "/cmd_vel"
    imu: str = "/imu"
    wheel_odom: str = "/wheel_odom"
    rocks: str = "/rocks"
    ground_truth: str = "/ground_truth"
    left_image: str = "/stereo/left/image_raw"
    right_image: str = "/stereo/right/image_raw"
    left_info: str = "/stereo/left/camera_info"
    right_info: str = "/stereo/right/camera_info"
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    catalog: str = "/catalog"
    kinds: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        named = [(f.name, getattr(self, f.name)) for f in fields(self) if f.name != "kinds"]
        if not isinstance(self.kinds, Mapping):
            raise ConfigError(f"TopicNames.kinds must map kind names to topics, got {self.kinds!r}")
        named += [(f"kinds[{k!r}]", v) for k, v in self.kinds.items()]
        for where, name in named:
            if not isinstance(name, str) or not name:
                raise ConfigError(f"TopicNames.{where} must be a non-empty string, got {name!r}")
        names = [n for _, n in named]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise ConfigError(f"TopicNames must be distinct: {twice} named for several roles")

    def topic_of(self, kind: str, codec: BagCodec) -> str:
        """The topic of landmark kind ``kind`` (encoded by ``codec``)."""
        if kind == "rocks":
            return self.rocks
        return self.kinds.get(kind, codec.default_topic)

    def as_roles(self) -> dict[str, str]:
        """Role -> topic, every role (landmark kinds other than rocks by their kind name)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "kinds"}
        out.update(self.kinds)
        return out


def topic_roles(kind_names: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The roles a topic map may name: the fixed ones, then the landmark kinds ``kind_names``."""
    fixed = tuple(f.name for f in fields(TopicNames) if f.name != "kinds")
    return fixed + tuple(k for k in kind_names if k not in fixed)


def topic_names(mapping: Mapping[str, str] | None, kind_names: tuple[str, ...] = (),
                base: TopicNames | None = None) -> TopicNames:
    """:class:`TopicNames` from a role -> topic map (``--topic ROLE=NAME``, a ``topics:`` block) over
    ``base`` (default: the defaults). A role is a field of TopicNames or a landmark kind's name in
    ``kind_names``; an unknown role raises :class:`ConfigError` listing the valid ones."""
    base = base or TopicNames()
    if not mapping:
        return base
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"topics must map roles to topic names, got {type(mapping).__name__}")
    roles = topic_roles(kind_names)
    unknown = [r for r in mapping if r not in roles]
    if unknown:
        raise ConfigError(f"topics: unknown role(s) {unknown}; roles are {', '.join(roles)}")
    for role, name in mapping.items():
        if not isinstance(name, str) or not name.startswith("/"):
            raise ConfigError(f"topics.{role}: a topic name starting with '/', got {name!r}")
    fixed = {r: n for r, n in mapping.items() if r in {f.name for f in fields(TopicNames)}}
    kinds = {**base.kinds, **{r: n for r, n in mapping.items() if r not in fixed}}
    if "rocks" in kinds:  # the rock kind's topic is the field
        fixed["rocks"] = kinds.pop("rocks")
    return TopicNames(**{**{f.name: getattr(base, f.name) for f in fields(TopicNames) if f.name != "kinds"},
                         **fixed, "kinds": kinds})


def parse_topic_options(options: list[str] | tuple[str, ...]) -> dict[str, str]:
    """``["imu=/imu/data", ...]`` (repeated ``--topic ROLE=NAME``) -> {role: topic}."""
    out: dict[str, str] = {}
    for text in options or ():
        role, sep, name = str(text).partition("=")
        if not sep or not role.strip() or not name.strip():
            raise ConfigError(f"--topic must be ROLE=NAME (e.g. imu=/imu/data), got {text!r}")
        if role.strip() in out:
            raise ConfigError(f"--topic gives role {role.strip()!r} twice")
        out[role.strip()] = name.strip()
    return out


@dataclass(frozen=True)
class BagEncoding:
    """Covariances written into messages (the measurement types carry none of these).

    Sigmas are 1-sigma, diagonal. ``rock_rotation_var`` fills the rotation block of each rock's
    6x6 pose covariance: a rock centre has no orientation, so the block says "unknown".
    """

    rock_rotation_var: float = 1.0e6  # rad^2
    imu_orientation_sigma_rad: tuple[float, float, float] = (0.01, 0.01, 0.05)
    imu_gyro_sigma_radps: float = 0.005
    imu_accel_sigma_mps2: float = 0.05
    wheel_v_sigma_mps: float = 0.02
    wheel_yaw_rate_sigma_radps: float = 0.02
    unknown_var: float = 1.0e6  # fills pose covariances of wheel odometry (pose not measured)


def register_vision_msgs(store: Typestore) -> None:
    """Register the vision_msgs types into ``store`` (no-op for types it already has)."""
    missing = {k: v for k, v in VISION_MSGS.items() if k not in store.fielddefs}
    typs = {}
    for name, text in missing.items():
        typs.update(get_types_from_msg(text, name))
    if typs:
        store.register(typs)


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy typestore with vision_msgs registered (shared, do not mutate further)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    register_vision_msgs(store)
    return store


def stamp_s(ns: int) -> float:
    """Integer nanoseconds (a header stamp) -> float seconds."""
    return ns / 1e9


class BagCodecError(RelocError):
    """A landmark message cannot be decoded."""


class MessageContentError(BagCodecError):
    """One message holds content that cannot become an observation (bad shape, bad covariance):
    the reader drops and counts it (or raises with ``repair=False``)."""


class UnknownFrameError(BagCodecError):
    """Detections are in a frame with no known transform to base_link: the whole bag is refused."""


class MessageBuilder(Protocol):
    """What an encoder gets from the writer: the typestore's classes, the base frame, the
    covariances to write, and builders of the common sub-messages."""

    types: Mapping[str, Any]
    frame_base: str
    enc: BagEncoding

    def header(self, ns: int, frame_id: str) -> Any: ...
    def vec3(self, v) -> Any: ...
    def pose(self, p, q) -> Any: ...


@dataclass(frozen=True)
class DecodeContext:
    """What a decoder gets from the reader: its config (``fgslam.io.BagReaderConfig``: base frame,
    default sigmas, class ids) and ``T_base_frame`` (frame name -> (4, 4) transform to base_link,
    the base frame included)."""

    config: Any
    T_base_frame: Mapping[str, np.ndarray]


@dataclass(frozen=True)
class CdrParser:
    """A way past rosbags' deserializer for one message type: ``parse(raw CDR bytes)`` gives what
    the kind's decoder takes, with its header's stamp as ``stamp_ns``, or None for bytes it does
    not read (rosbags deserializes that message then); used only on a bag whose typestore it
    ``accepts`` (the same definitions)."""

    msgtype: str
    parse: Callable[[bytes | memoryview], Any]
    accepts: Callable[[Any], bool]


@dataclass(frozen=True)
class BagCodec:
    """How one landmark kind travels in a bag: ``msgtypes`` accepted on read (the first is
    written), ``default_topic``, ``decoder(ctx) -> (msg, ns) -> observation`` (raising
    :class:`MessageContentError` / :class:`~reloc.errors.MeasurementError` for a bad message,
    :class:`UnknownFrameError` for an unknown frame), ``encode(obs, ns, builder) -> msg`` and,
    optionally, a ``parser`` whose output the decoder takes as well as a deserialized message."""

    msgtypes: tuple[str, ...]
    default_topic: str
    decoder: Callable[[DecodeContext], Callable[[Any, int], Any]]
    encode: Callable[[Any, int, MessageBuilder], Any]
    parser: CdrParser | None = None


def check_transform(name: str, T, base_frame: str) -> np.ndarray:
    """A finite rigid (4, 4) ``T_base_<name>``; raises :class:`BagCodecError` naming the frame."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BagCodecError(f"camera_frames[{name!r}] must be a finite (4, 4) transform, got {T.shape}")
    R = T[:3, :3]
    if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
        raise BagCodecError(f"camera_frames[{name!r}] rotation block is not a rotation matrix")
    if name == base_frame and not np.allclose(T, np.eye(4)):
        raise BagCodecError(f"camera_frames[{name!r}] redefines the base frame")
    return T

"""ROS 2 message conventions of fgslam bags: topic names, message types, and vision_msgs.

vision_msgs is not part of the rosbags Jazzy typestore, so its definitions are registered here
from the .msg text of the ROS 2 Jazzy release (vision_msgs 4.x). Bags embed their schemas, so
only writers (and readers of old bags without embedded definitions) need :func:`typestore`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

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

ROCK_CLASS_ID = "rock"
WORLD_FRAME = "world"
BASE_FRAME = "base_link"


@dataclass(frozen=True)
class TopicNames:
    """Topic names of a bag. Required on read: ``imu``, ``rocks`` and one of ``cmd_vel`` /
    ``wheel_odom``; ``ground_truth`` is optional."""

    cmd_vel: str = "/cmd_vel"
    imu: str = "/imu"
    wheel_odom: str = "/wheel_odom"
    rocks: str = "/rocks"
    ground_truth: str = "/ground_truth"

    def __post_init__(self) -> None:
        names = [getattr(self, f.name) for f in fields(self)]
        for f, name in zip(fields(self), names):
            if not isinstance(name, str) or not name:
                raise ValueError(f"TopicNames.{f.name} must be a non-empty string, got {name!r}")
        if len(set(names)) != len(names):
            raise ValueError(f"TopicNames must be distinct, got {names}")


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

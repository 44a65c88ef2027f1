"""What makes a simulated bag look like a rover's recording: its style (start epoch, stamped or
unstamped commands, image compression) and its scene (the stereo camera's calibration and
mounting, the frame tree, the orbital catalog as markers), written by :func:`sim.bag_writer.write_bag`.

Frames (``reloc.bag_spec``): ``world`` -> ``base_link`` on ``/tf`` at every ground-truth pose
(the true pose, so viewers place the rover and its rock detections where they are), ``world`` ->
``odom`` (the start pose, where odometry starts), ``base_link`` -> ``stereo_left_optical`` (the
camera mounting) and ``stereo_left_optical`` -> ``stereo_right_optical`` (the baseline) on
``/tf_static``, latched (transient-local QoS) as ``robot_state_publisher`` offers it.
"""

from __future__ import annotations

import dataclasses

import datetime
from dataclasses import dataclass
from typing import Literal

import numpy as np

from reloc.bag_spec import (
    BASE_FRAME,
    LEFT_CAMERA_FRAME,
    ODOM_FRAME,
    RIGHT_CAMERA_FRAME,
    WORLD_FRAME,
    TopicNames,
)
from reloc.camera_bag import CameraCalibration
from sim.errors import SimError


@dataclass(frozen=True)
class BagStyle:
    """How a bag is written: ``epoch_ns`` added to every stamp (0: stamps are stream seconds, as
    the yards' results are defined; a real-looking bag starts at e.g. 2026-01-01), ``cmd_vel_stamped``
    (TwistStamped; False: an unstamped Twist, timed by its log time, as many rovers publish it),
    ``image_format`` of the stereo images ("raw" sensor_msgs/Image mono8, or a CompressedImage in
    "png" (lossless) or "jpeg"), ``tf`` (write /tf, /tf_static and the catalog markers; off by
    default so that a bag holds only the measurements given)."""

    epoch_ns: int = 0
    cmd_vel_stamped: bool = True
    image_format: Literal["raw", "png", "jpeg"] = "png"
    tf: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.epoch_ns, int) or self.epoch_ns < 0:
            raise SimError(f"BagStyle.epoch_ns must be an integer >= 0, got {self.epoch_ns!r}")
        if self.image_format not in ("raw", "png", "jpeg"):
            raise SimError(f"BagStyle.image_format must be raw, png or jpeg, got {self.image_format!r}")


ROBOT_EPOCH_NS = 1_767_225_600 * 1_000_000_000  # 2026-01-01T00:00:00Z: a real-looking first stamp

# The topics and types of a rover as its drivers publish them (Husky / Clearpath style): an
# unstamped Twist command, /imu/data, wheel odometry on /odom, compressed stereo images.
ROBOT_TOPICS = TopicNames(cmd_vel="/cmd_vel", imu="/imu/data", wheel_odom="/odom", ground_truth="/ground_truth",
                          left_image="/stereo/left/image_raw", right_image="/stereo/right/image_raw",
                          left_info="/stereo/left/camera_info", right_info="/stereo/right/camera_info",
                          catalog="/orbital/catalog")


def bag_style(name: str, epoch_ns: int | None = None) -> tuple[BagStyle, TopicNames]:
    """The (style, topics) of a named bag style: ``fgslam`` (fgslam's own topics, stamps from 0,
    /tf and the catalog markers) or ``robot`` (:data:`ROBOT_TOPICS`, an unstamped Twist, PNG
    compressed images, stamps from 2026-01-01); ``epoch_ns`` replaces the style's start epoch."""
    if name == "fgslam":
        style = BagStyle(tf=True)
        topics = TopicNames()
    elif name == "robot":
        style = BagStyle(epoch_ns=ROBOT_EPOCH_NS, cmd_vel_stamped=False, image_format="png", tf=True)
        topics = ROBOT_TOPICS
    else:
        raise SimError(f"--bag-style must be fgslam or robot, got {name!r}")
    if epoch_ns is not None:
        style = BagStyle(epoch_ns=epoch_ns, cmd_vel_stamped=style.cmd_vel_stamped,
                         image_format=style.image_format, tf=style.tf)
    return style, topics


def bag_description(style: BagStyle | None, topics: TopicNames | None, images: bool = False) -> dict:
    """How a simulated bag was written, for world.yaml: its style (epoch, stamped command, image
    format, /tf), whether it holds stereo images, and its topic names (so that ``fgslam run`` can
    be given the same ``--topic`` map the bag needs)."""
    style, topics = style or BagStyle(), topics or TopicNames()
    named = {f.name: getattr(topics, f.name) for f in dataclasses.fields(topics)
             if isinstance(getattr(topics, f.name), str)}
    return {"epoch_ns": int(style.epoch_ns), "cmd_vel_stamped": bool(style.cmd_vel_stamped),
            "images": bool(images), "image_format": style.image_format if images else None,
            "tf": bool(style.tf), "topics": named}


def parse_epoch(text: str | None) -> int | None:
    """``--epoch``: seconds since 1970 (``1767225600``) or an ISO date/time in UTC
    (``2026-01-01``, ``2026-01-01T08:30:00Z``) -> integer ns (None -> None: the style's own)."""
    if text is None:
        return None
    if str(text).strip() in ("", "0"):
        return 0
    text = str(text).strip()
    try:
        return int(round(float(text) * 1e9))
    except ValueError:
        pass
    try:
        when = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise SimError(f"--epoch must be seconds since 1970 or an ISO date (2026-01-01T00:00:00Z), got {text!r}") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=datetime.UTC)
    return int(round(when.timestamp())) * 1_000_000_000


@dataclass(frozen=True)
class BagScene:
    """The scene of a bag: ``left``/``right`` cameras (None: no images), ``T_base_cam`` (4, 4) the
    left optical frame in base_link, ``T_world_odom`` (4, 4) where odometry starts, and the orbital
    ``catalog_xy_m`` (N, 2) / ``catalog_size_m`` (N,) drawn as markers (None: none)."""

    left: CameraCalibration | None = None
    right: CameraCalibration | None = None
    T_base_cam: np.ndarray | None = None
    T_world_odom: np.ndarray | None = None
    catalog_xy_m: np.ndarray | None = None
    catalog_size_m: np.ndarray | None = None

    def static_transforms(self) -> list[tuple[str, str, np.ndarray]]:
        out = []
        if self.T_world_odom is not None:
            out.append((WORLD_FRAME, ODOM_FRAME, np.asarray(self.T_world_odom, float)))
        if self.T_base_cam is not None:
            out.append((BASE_FRAME, LEFT_CAMERA_FRAME, np.asarray(self.T_base_cam, float)))
        if self.right is not None and self.right.P[0, 0] > 0:
            T = np.eye(4)
            T[0, 3] = -self.right.P[0, 3] / self.right.P[0, 0]  # the baseline along the left x axis
            out.append((LEFT_CAMERA_FRAME, RIGHT_CAMERA_FRAME, T))
        return out


def stereo_scene(stereo_cfg, width_px: int, T_world_odom=None, catalog=None) -> BagScene:
    """The scene of the simulator's rendered mast camera (``sim.datasets.rover_camera``)."""
    from sim.datasets import rover_camera
    from sim.sensors.stereo import StereoCamera

    cam = rover_camera(stereo_cfg, width_px)
    left = CameraCalibration.rectified(cam.width_px, cam.height_px, cam.f_px, cam.cx_px, cam.cy_px,
                                       frame_id=LEFT_CAMERA_FRAME)
    right = CameraCalibration.rectified(cam.width_px, cam.height_px, cam.f_px, cam.cx_px, cam.cy_px,
                                        -cam.f_px * stereo_cfg.baseline_m, frame_id=RIGHT_CAMERA_FRAME)
    return BagScene(left, right, StereoCamera.from_config(stereo_cfg).T_base_cam, T_world_odom,
                    *catalog_arrays(catalog))


def catalog_arrays(catalog) -> tuple[np.ndarray | None, np.ndarray | None]:
    if catalog is None or len(catalog) == 0:
        return None, None
    xy = np.asarray(catalog.xy_m)
    return xy[:, :2], np.asarray(catalog.size_m)


def latched_qos():
    """The transient-local, keep-last-1 QoS that /tf_static and latched markers are offered with."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    never = QosTime(sec=0, nsec=0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, never, never,
                QosLiveliness.AUTOMATIC, never, False)]

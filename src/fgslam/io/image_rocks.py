"""Rocks from a bag's stereo images: the image front-end of a real rover's recording.

A rover records its stereo pair (``sensor_msgs/Image`` or ``CompressedImage``), the cameras'
``CameraInfo`` and its frames (``/tf_static``), not rock detections. :class:`StereoBag` reads
that setup from the bag: the left and right image topics (a role's topic, or that topic with
``/compressed`` as ``image_transport`` names it), the first CameraInfo of each camera (intrinsics;
the baseline from the right camera's projection, ``-P[0, 3] / P[0, 0]``), and the mounting
``T_base_cam`` of the left camera's optical frame from ``/tf_static`` (or the config). It pairs
left and right images by header stamp (within ``pair_tolerance_s``), decodes and rectifies them,
and :func:`detect_rocks` runs the shared front-end (:class:`reloc.stereo_frontend.StereoFrontEnd`:
ONNX rover detector + stereo triangulation) on every pair, giving one
:class:`~reloc.measurements.RockObservations` per pair in base_link, as the simulator's image path
does for a rendered pair. The codecs live in :mod:`reloc.camera_bag`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fgslam.errors import BagError
from reloc.bag_spec import (
    CAMERA_INFO_TYPE,
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    TopicNames,
    ros2_msgtype,
)
from reloc.camera_bag import (
    ImageDecodeError,
    Rectifier,
    decode_camera_info,
    decode_image,
    resolve_transform,
    static_transforms,
    stereo_rig,
)
from reloc.config import NonNegative, Positive, checked
from reloc.errors import ConfigError
from reloc.measurements import RockObservations
from reloc.stereo_frontend import FrontEndConfig, StereoFrontEnd

log = logging.getLogger(__name__)

IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)


@dataclass(frozen=True)
@checked(ConfigError)
class ImageInputConfig:
    """How a bag's stereo images become rocks: ``pair_tolerance_s`` (left and right stamps closer
    than this are one pair), ``T_base_cam`` (16 numbers, the left optical frame in base_link,
    row-major; None: from /tf_static), ``baseline_m`` (None: from the right CameraInfo),
    ``base_frame`` (the body frame of /tf_static) and the front-end's range gate and detector."""

    pair_tolerance_s: NonNegative = 0.005
    T_base_cam: tuple[float, ...] | None = None
    baseline_m: Positive | None = None
    base_frame: str = "base_link"
    front_end: FrontEndConfig = field(default_factory=FrontEndConfig)

    def __post_init__(self) -> None:
        if self.T_base_cam is not None:
            T = np.asarray(self.T_base_cam, dtype=float)
            if T.size != 16 or not np.allclose(T.reshape(4, 4)[3], [0, 0, 0, 1]):
                raise ConfigError(f"images.T_base_cam must be 16 numbers (a 4x4 transform, row-major, last row "
                                  f"0 0 0 1), got {list(self.T_base_cam)}")


def _image_topic(info: dict, name: str) -> str | None:
    """``name`` when the bag has it, else ``name/compressed`` (image_transport's), else None."""
    for topic in (name, name.rstrip("/") + "/compressed"):
        if topic in info and info[topic].msgcount > 0:
            return topic
    return None


def has_images(path: Path, topics: TopicNames) -> bool:
    """Whether the bag at ``path`` holds both stereo image topics of ``topics``."""
    from fgslam.io.bag_reader import _open, _resolve

    reader = _open(_resolve(Path(path)), Path(path))
    try:
        info = reader.topics
        return _image_topic(info, topics.left_image) is not None and _image_topic(info, topics.right_image) is not None
    finally:
        reader.close()


class StereoBag:
    """The stereo setup of a bag and its image pairs (see module doc); checked when made."""

    def __init__(self, path: str | Path, topics: TopicNames | None = None,
                 config: ImageInputConfig | None = None) -> None:
        from fgslam.io.bag_reader import _open, _resolve

        self.path = Path(path)
        self.topics = topics or TopicNames()
        self.config = config or ImageInputConfig()
        self._bag = _resolve(self.path)
        reader = _open(self._bag, self.path)
        try:
            self._setup(reader)
        finally:
            reader.close()

    def _fail(self, info, what: str) -> BagError:
        listing = ", ".join(f"{t} ({i.msgtype}, {i.msgcount})" for t, i in sorted(info.items())) or "none"
        return BagError(f"bag {self.path}: {what}; topics present: {listing}; map them with --topic "
                        "left_image=NAME --topic right_image=NAME --topic left_info=NAME --topic right_info=NAME")

    def _setup(self, reader) -> None:
        info, t, cfg = reader.topics, self.topics, self.config
        self.left_topic, self.right_topic = _image_topic(info, t.left_image), _image_topic(info, t.right_image)
        missing = [n for n, got in ((t.left_image, self.left_topic), (t.right_image, self.right_topic)) if got is None]
        if missing:
            raise self._fail(info, f"stereo image topic(s) missing or empty: {', '.join(missing)} (or .../compressed)")
        for topic, types in ((self.left_topic, IMAGE_TYPES), (self.right_topic, IMAGE_TYPES),
                             (t.left_info, (CAMERA_INFO_TYPE,)), (t.right_info, (CAMERA_INFO_TYPE,))):
            if topic not in info or info[topic].msgcount == 0:
                raise self._fail(info, f"camera topic {topic} missing or empty")
            if info[topic].msgtype not in types:  # the ROS 2 form (fgslam.io.bag_reader.OpenBag)
                raise BagError(f"bag {self.path}: topic {topic} has type {info[topic].msgtype or 'mixed'}, expected "
                               f"{' or '.join(types)}")
        self.n_pairs = min(info[self.left_topic].msgcount, info[self.right_topic].msgcount)
        try:
            self.left, self.right = (decode_camera_info(self._first(reader, topic)) for topic in (t.left_info, t.right_info))
            self.rig = stereo_rig(self.left, self.right, cfg.baseline_m)
            self.rectify_left, self.rectify_right = Rectifier(self.left), Rectifier(self.right)
            self.T_base_cam = self._mounting(reader)
        except ImageDecodeError as exc:
            raise BagError(f"bag {self.path}: {exc}") from None

    def _first(self, reader, topic: str):
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            return reader.decode(conn, raw)
        raise BagError(f"bag {self.path}: topic {topic} holds no message")

    def _mounting(self, reader) -> np.ndarray:
        cfg = self.config
        if cfg.T_base_cam is not None:
            return np.asarray(cfg.T_base_cam, dtype=float).reshape(4, 4)
        frame = self.left.frame_id.lstrip("/")
        if not frame:
            raise ImageDecodeError(f"{self.topics.left_info} has no frame_id: give images.T_base_cam in the config")
        conns = [c for c in reader.connections if c.topic == self.topics.tf_static]
        msgs = (reader.decode(conn, raw) for conn, _, raw in reader.messages(connections=conns))
        return resolve_transform(static_transforms(msgs), cfg.base_frame, frame)

    def pairs(self, after_ns: int | None = None) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(stamp ns, left, right) of every pair, rectified (H, W) uint8, in stamp order; pairs
        stamped at or before ``after_ns`` are skipped undecoded. Unpaired images are logged."""
        from fgslam.io.bag_reader import _open

        tol_ns = round(self.config.pair_tolerance_s * 1e9)
        reader = _open(self._bag, self.path)
        pending: dict[str, dict[int, tuple]] = {self.left_topic: {}, self.right_topic: {}}
        other = {self.left_topic: self.right_topic, self.right_topic: self.left_topic}
        n_unpaired = 0
        try:
            conns = [c for c in reader.connections if c.topic in pending]
            for conn, _, raw in reader.messages(connections=conns):
                msg, msgtype = reader.decode(conn, raw), ros2_msgtype(conn.msgtype)
                ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                waiting = pending[other[conn.topic]]
                match = min(waiting, key=lambda s: abs(s - ns), default=None)
                if match is None or abs(match - ns) > tol_ns:
                    pending[conn.topic][ns] = (msg, msgtype)
                    for side in pending.values():  # a frame a whole second old gets no partner any more
                        for s in [s for s in side if s < ns - 1_000_000_000]:
                            del side[s]
                            n_unpaired += 1
                    continue
                mate = waiting.pop(match)
                left, right = ((msg, msgtype), mate) if conn.topic == self.left_topic else (mate, (msg, msgtype))
                t_ns = min(ns, match)
                if after_ns is not None and t_ns <= after_ns:
                    continue
                try:
                    yield t_ns, self.rectify_left(decode_image(*left)), self.rectify_right(decode_image(*right))
                except ImageDecodeError as exc:
                    raise BagError(f"bag {self.path}: image pair at stamp {t_ns} ns: {exc}") from None
        finally:
            reader.close()
        n_unpaired += sum(len(side) for side in pending.values())
        if n_unpaired:
            log.warning("bag %s: %d stereo image(s) without a partner within %g s were skipped",
                        self.path, n_unpaired, self.config.pair_tolerance_s)

    def front_end(self, detector=None) -> StereoFrontEnd:
        """The front-end of this rig and mounting (``detector``: default the shipped rover model)."""
        return StereoFrontEnd(self.rig, self.T_base_cam, self.config.front_end, detector=detector)


@dataclass
class DetectStats:
    """Frames processed, rocks found, and seconds spent decoding, detecting and triangulating."""

    n_frames: int = 0
    n_rocks: int = 0
    decode_s: float = 0.0
    detect_s: float = 0.0
    stereo_s: float = 0.0

    @property
    def frames_per_s(self) -> float:
        total = self.decode_s + self.detect_s + self.stereo_s
        return self.n_frames / total if total > 0 else float("nan")


def detect_rocks(stereo: StereoBag, front: StereoFrontEnd | None = None, after_ns: int | None = None,
                 on_frame: Callable[[int, RockObservations], None] | None = None,
                 stats: DetectStats | None = None) -> Iterator[tuple[int, RockObservations]]:
    """(stamp ns, RockObservations in base_link) of every stereo pair after ``after_ns``;
    ``on_frame`` is called with each; ``stats`` (if given) is filled as frames pass."""
    import time

    front = front or stereo.front_end()
    stats = stats if stats is not None else DetectStats()
    pairs = stereo.pairs(after_ns)
    while True:
        t0 = time.perf_counter()
        item = next(pairs, None)
        stats.decode_s += time.perf_counter() - t0
        if item is None:
            return
        ns, left, right = item
        fr = front.frame(ns / 1e9, left, right)
        stats.n_frames += 1
        stats.n_rocks += len(fr.observations)
        stats.detect_s += fr.detect_s
        stats.stereo_s += fr.stereo_s
        if on_frame is not None:
            on_frame(ns, fr.observations)
        yield ns, fr.observations


class ImageRockSource:
    """A bag whose rocks come from its stereo images: its measurement stream
    (:class:`fgslam.io.bag_reader.BagSource`, no landmark topic needed) merged in time order with
    the rocks :func:`detect_rocks` finds, detected once (:meth:`detect`, or at the first
    iteration) and kept in memory. It offers what a BagSource offers to the runner."""

    def __init__(self, path: str | Path, topics: TopicNames | None = None,
                 config: ImageInputConfig | None = None, **bag_options) -> None:
        from fgslam.io.bag_reader import BagSource

        topics = topics or TopicNames()
        self.bag = BagSource(path, topics, require_landmarks=False, **bag_options)
        self.stereo = StereoBag(path, topics, config)
        self.path = self.bag.path
        self.stats = DetectStats()
        self._rocks: list[RockObservations] | None = None

    def detect(self, progress: Callable[[int, int], None] | None = None) -> list[RockObservations]:
        """The rocks of every pair (detected at the first call); ``progress(done, total)`` per pair."""
        if self._rocks is None:
            rocks = []
            for _, obs in detect_rocks(self.stereo, stats=self.stats):
                rocks.append(obs)
                if progress is not None:
                    progress(len(rocks), self.stereo.n_pairs)
            self._rocks = rocks
            log.info("bag %s: %d rocks in %d stereo pairs, %.2f frames/s", self.path, self.stats.n_rocks,
                     self.stats.n_frames, self.stats.frames_per_s)
        return self._rocks

    def __iter__(self) -> Iterator:
        import heapq

        from reloc.measurements import sort_key

        return heapq.merge(iter(self.bag), self.detect(), key=sort_key)

    @property
    def message_counts(self) -> dict[str, int]:
        return {**self.bag.message_counts, "stereo pairs": self.stereo.n_pairs}

    @property
    def report(self):
        return self.bag.report

    def ground_truth(self) -> Iterator:
        return self.bag.ground_truth()

    def first_of(self, cls: type):
        if cls is RockObservations:
            return next(iter(self.detect()), None)
        return self.bag.first_of(cls)

    def motion_only(self) -> Iterator:
        return self.bag.motion_only()

    def span_s(self) -> tuple[float, float]:
        return self.bag.span_s()

    def first_stamp_s(self) -> float:
        rocks = self.detect()
        return min(self.bag.first_stamp_s(), rocks[0].t) if rocks else self.bag.first_stamp_s()

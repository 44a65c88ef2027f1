"""Read a ROS 2 bag into one time-ordered stream of typed measurements.

The same path serves simulated bags (``sim.bag_writer``) and real recordings: any rosbag2
directory (MCAP or SQLite3 storage, with ``metadata.yaml``) or a bare ``.mcap`` / ``.db3`` file
holding the topics of :class:`~reloc.bag_spec.TopicNames`. Motion inputs and ground truth have
fixed roles; every registered landmark kind with a bag layer (:mod:`reloc.kinds`) is one more
role, decoded by its codec. Bags embed their message definitions; for bags that do not, the
Jazzy typestore with vision_msgs is the fallback.

Measurement time is the header stamp (integer ns -> float s), not the recording time; only an
unstamped ``geometry_msgs/Twist`` on the command topic falls back to the log time. Stamps are
checked per topic: messages older than an earlier one are counted as reordered and sorted (within
``BagReaderConfig.reorder_window_s``; older still, they are dropped as late); exact duplicates
(same stamp, same content) are dropped; same-stamp messages with different content keep the first
one recorded; messages with NaN/inf or otherwise invalid content are dropped.
Every such repair is counted in :class:`BagReport` and logged at WARNING. With
``repair=False`` each of them raises :class:`~fgslam.errors.BagError` instead.

The bag is streamed (:class:`BagSource`): a kilometre traverse is never held in memory, and
:func:`read_bag` is the same stream collected into a list.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.errors import BagError
from fgslam.io.bag_decode import (
    BagReaderConfig,
    decode_cmd_vel,
    decode_ground_truth,
    decode_imu,
    decode_wheel_odom,
)
from fgslam.io.bag_merge import BagPass
from fgslam.io.bag_report import BagReport, BagStream, TopicReport, check_kept, log_repairs
from fgslam.io.cdr_batch import batch_cmd_vel, batch_ground_truth, batch_imu, batch_wheel_odom
from reloc.bag_spec import (
    CMD_VEL_TYPE,
    CMD_VEL_UNSTAMPED_TYPE,
    IMU_TYPE,
    ODOMETRY_TYPE,
    BagCodecError,
    DecodeContext,
    TopicNames,
    check_transform,
    typestore,
)
from reloc.kinds import UnknownKindError, kind_named, kinds_with
from reloc.measurements import Measurement

log = logging.getLogger(__name__)

__all__ = ["BagReport", "BagSource", "BagStream", "TopicReport", "read_bag"]


@dataclass(frozen=True)
class _Role:
    name: str
    topic: str
    msgtypes: tuple[str, ...]
    decode: Callable  # one deserialized message -> measurement
    landmark: bool = False  # the topic of a landmark kind
    batch: Callable | None = None  # a decoded block (fgslam.io.cdr_batch) -> (ns, measurements)


def _resolve(path: Path) -> Path:
    """The path rosbags should open: a rosbag2 directory or a single storage file."""
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        files = sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3"))
        if len(files) == 1:
            log.info(
                "bag %s has no metadata.yaml; reading its storage file %s", path, files[0].name
            )
            return files[0]
        raise BagError(
            f"bag {path} is not a rosbag2 directory: no metadata.yaml and "
            f"{len(files)} storage files (.mcap/.db3)"
        )
    if path.name == "metadata.yaml":
        return path.parent
    if path.suffix in (".mcap", ".db3"):
        return path
    raise BagError(
        f"bag {path} is not a ROS 2 bag: expected a rosbag2 directory or a .mcap/.db3 file"
    )


def _open(bag: Path, path: Path):
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([bag], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises many kinds on garbage input; all mean "not readable"
        hint = ""
        if "end magic" in str(exc):
            hint = (
                " (an MCAP file without its footer, e.g. from an interrupted recording, can be "
                "repaired with `mcap recover` or `ros2 bag reindex`)"
            )
        raise BagError(
            f"bag {path} cannot be opened (not a valid or a truncated bag): "
            f"{type(exc).__name__}: {exc}{hint}"
        ) from exc
    return reader


def _check_topics(reader, roles: list[_Role], path: Path, require_landmarks: bool = True) -> dict[str, object]:
    """Validate topic presence and types; return topic -> connections to read."""
    info = reader.topics
    present = {r.name: r.topic in info and info[r.topic].msgcount > 0 for r in roles}
    listing = (
        ", ".join(f"{t} ({i.msgtype}, {i.msgcount})" for t, i in sorted(info.items())) or "none"
    )
    by_name = {r.name: r for r in roles}
    missing = [by_name["imu"].topic] if not present["imu"] else []
    landmarks = [r for r in roles if r.landmark]
    if require_landmarks and not any(present[r.name] for r in landmarks):  # at least one landmark kind
        missing.append(" or ".join(r.topic for r in landmarks) or "a landmark topic (no kind selected)")
    if not (present["cmd_vel"] or present["wheel_odom"]):
        missing.append(f"{by_name['cmd_vel'].topic} or {by_name['wheel_odom'].topic}")
    if missing:
        raise BagError(
            f"bag {path}: required topic(s) missing or empty: {', '.join(missing)}; "
            f"topics present: {listing}; map a role to a topic of the bag with --topic ROLE=NAME "
            f"or a topics: block in --config (roles: {', '.join(r.name for r in roles)}; rocks can also come "
            "from stereo images: left_image, right_image, left_info, right_info)"
        )
    selected = {}
    for r in roles:
        if not present[r.name]:
            continue
        msgtype = info[r.topic].msgtype
        if msgtype not in r.msgtypes:
            raise BagError(
                f"bag {path}: topic {r.topic} has type {msgtype or 'mixed'}, "
                f"expected {' or '.join(r.msgtypes)}"
            )
        selected[r.topic] = info[r.topic].connections
    return selected


def _frames(config: BagReaderConfig, camera_frames: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """``T_base_frame`` of every named frame (the base frame is the identity), validated."""
    out = {config.base_frame: np.eye(4)}
    for name, T in (camera_frames or {}).items():
        try:
            out[name] = check_transform(name, T, config.base_frame)
        except BagCodecError as exc:
            raise BagError(str(exc)) from None
    return out


def _landmark_roles(topics: TopicNames, kinds: Sequence[str] | None, ctx: DecodeContext) -> list[_Role]:
    """One role per landmark kind read: every registered kind with a bag layer, or ``kinds``."""
    try:
        unknown = [k for k in topics.kinds if k not in {kd.name for kd in kinds_with("bag")}]
        if unknown:
            kind_named(unknown[0])  # raises for an unregistered name
            raise BagError(f"TopicNames.kinds names kind {unknown[0]!r}, which has no bag layer")
        chosen = kinds_with("bag") if kinds is None else [kind_named(k) for k in kinds]
    except UnknownKindError as exc:
        raise BagError(f"cannot read landmark kinds: {exc}") from None
    roles = []
    for kind in chosen:
        if not kind.has("bag"):
            raise BagError(f"landmark kind {kind.name!r} has no bag layer: it cannot be read from a bag")
        codec = kind.layer("bag")
        roles.append(_Role(kind.name, topics.topic_of(kind.name, codec), tuple(codec.msgtypes),
                           codec.decoder(ctx), landmark=True))
    return roles


def _roles(topics: TopicNames, kinds: Sequence[str] | None, ctx: DecodeContext) -> list[_Role]:
    return [
        _Role("cmd_vel", topics.cmd_vel, (CMD_VEL_TYPE, CMD_VEL_UNSTAMPED_TYPE), decode_cmd_vel, batch=batch_cmd_vel),
        _Role("wheel_odom", topics.wheel_odom, (ODOMETRY_TYPE,), decode_wheel_odom, batch=batch_wheel_odom),
        _Role("imu", topics.imu, (IMU_TYPE,), decode_imu, batch=batch_imu),
        *_landmark_roles(topics, kinds, ctx),
        _Role("ground_truth", topics.ground_truth, (ODOMETRY_TYPE,), decode_ground_truth, batch=batch_ground_truth),
    ]


class BagSource:
    """A bag as a lazily decoded, time-ordered measurement stream that can be iterated again.

    Each iteration opens the bag, decodes its messages in blocks of :data:`BLOCK` (the motion
    messages vectorised, :mod:`fgslam.io.cdr_batch`) and yields measurements in
    :func:`reloc.measurements.sort_key` order, holding only ``reorder_window_s`` of stream in
    memory: the repairs of the module doc are applied as the messages pass. A message stamped
    more than the window before the newest stamp recorded before it cannot be put in order any
    more; it is dropped and counted as late (``repair=False``: raised). ``require_landmarks`` False
    accepts a bag without any landmark topic (its landmarks come from elsewhere, e.g. its images:
    :class:`fgslam.io.image_rocks.ImageRockSource`). The topics and their types are checked
    when the source is made; ``report`` is set after the first complete iteration (whose repairs
    are logged once), and a required topic none of whose messages was usable raises at its end.
    """

    def __init__(self, path: str | Path, topics: TopicNames | None = None, *,
                 camera_frames: dict[str, np.ndarray] | None = None, repair: bool = True,
                 config: BagReaderConfig | None = None, kinds: Sequence[str] | None = None,
                 require_landmarks: bool = True) -> None:
        self.path = Path(path)
        self.config = config or BagReaderConfig()
        self.repair = repair
        ctx = DecodeContext(self.config, _frames(self.config, camera_frames))  # extrinsics checked before any I/O
        self._roles = _roles(topics or TopicNames(), kinds, ctx)
        self._bag = _resolve(self.path)
        reader = _open(self._bag, self.path)
        try:
            self._topics = list(_check_topics(reader, self._roles, self.path, require_landmarks))
            self.message_counts = {t: int(reader.topics[t].msgcount) for t in self._topics}
            self._span_ns = (int(reader.start_time), int(reader.end_time))
        finally:
            reader.close()
        self.report: BagReport | None = None

    def __iter__(self) -> Iterator[Measurement]:
        return self._stream(self._roles)

    def ground_truth(self) -> Iterator[Measurement]:
        """The ground-truth measurements only, lazily (reads just that topic; nothing when the bag
        has none): a kilometre bag holds ~10^6 of them, held as objects they cost ~0.5 GB."""
        return self._only(("ground_truth",))

    def first_of(self, cls: type) -> Measurement | None:
        """The first measurement of type ``cls`` (reads only its topic, and stops there)."""
        role = {"CmdVel": "cmd_vel", "WheelOdometry": "wheel_odom", "ImuSample": "imu",
                "GroundTruthPose": "ground_truth"}.get(cls.__name__)
        it = self._only((role,)) if role else (m for m in self if isinstance(m, cls))
        return next(it, None)

    def motion_only(self) -> Iterator[Measurement]:
        """The commands, wheel odometry and IMU samples only (reads just those topics)."""
        return self._only(("cmd_vel", "wheel_odom", "imu"))

    def _only(self, names: tuple[str, ...]) -> Iterator[Measurement]:
        roles = [r for r in self._roles if r.name in names and r.topic in self._topics]
        return self._stream(roles, check=False) if roles else iter(())

    def span_s(self) -> tuple[float, float]:
        """(start, end) of the recording (s, log time: close to the stamps' span, known without reading)."""
        return self._span_ns[0] / 1e9, self._span_ns[1] / 1e9

    def first_stamp_s(self) -> float:
        """The stamp (s) of the stream's first measurement."""
        for m in self._stream(self._roles, check=False):
            return m.t
        raise BagError(f"bag {self.path}: no usable measurement")

    def _stream(self, roles: list[_Role], check: bool = True) -> Iterator[Measurement]:
        reader = _open(self._bag, self.path)
        try:
            merge = BagPass(roles, [r.topic for r in roles if r.topic in self._topics], reader,
                           self.path, self.repair, self.config.reorder_window_s)
            yield from merge.run()
        finally:
            reader.close()
        if check and roles is self._roles:
            reports = merge.reports()
            check_kept(reports, {r.name for r in roles if r.landmark}, self.path)
            if self.report is None:
                repairs = [line for r in reports.values() for line in log_repairs(r, self.path)]
                self.report = BagReport(path=self.path, topics=reports, repairs=tuple(repairs))


def read_bag(
    path: str | Path,
    topics: TopicNames | None = None,
    *,
    camera_frames: dict[str, np.ndarray] | None = None,
    repair: bool = True,
    config: BagReaderConfig | None = None,
    kinds: Sequence[str] | None = None,
) -> BagStream:
    """Read the whole bag at ``path`` (rosbag2 directory or .mcap/.db3 file) into a
    :class:`BagStream` (a :class:`BagSource` iterated once into memory).

    ``camera_frames`` maps a detection frame id to ``T_base_cam`` (4, 4), so landmarks reported
    in a camera frame are rotated and translated into base_link. ``kinds`` names the landmark
    kinds to read (default: every registered kind with a bag layer). Raises :class:`BagError`
    naming the bag, the topic and the problem on unreadable bags, missing required topics (imu,
    cmd_vel or wheel_odom, and a landmark topic), wrong message types, unknown frames, unknown
    kinds, and (``repair=False``) on any stamp or content problem that would otherwise be repaired.
    """
    source = BagSource(path, topics, camera_frames=camera_frames, repair=repair, config=config, kinds=kinds)
    measurements = list(source)
    log.info("read bag %s: %d measurements, %s", source.path, len(measurements),
             {t: r.n_kept for t, r in source.report.topics.items()})
    return BagStream(measurements, source.report)

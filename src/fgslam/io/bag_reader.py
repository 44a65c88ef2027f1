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

Other recorders' habits: ROS 1-style type names (``sensor_msgs/Image``) are read as their ROS 2
form (:func:`reloc.bag_spec.ros2_msgtype`), and a message that cannot be decoded is a
:class:`BagError` naming the bag, the topic and the cause (for a bag recorded with per-message
compression given as its bare storage file: the hint to give its directory). Every reader of
bags in :mod:`fgslam.io` opens them through :func:`_open` (an :class:`OpenBag`).

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
    CdrParser,
    DecodeContext,
    TopicNames,
    check_transform,
    ros2_msgtype,
    typestore,
)
from reloc.kinds import UnknownKindError, kind_named, kinds_with
from reloc.measurements import Measurement

log = logging.getLogger(__name__)

__all__ = ["BagReport", "BagSource", "BagStream", "OpenBag", "TopicReport", "read_bag"]

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"  # the first bytes of a zstd frame
PROBE_MESSAGES = 2048  # messages read at most, when a source is made, to decode each topic's first one


@dataclass(frozen=True)
class _Role:
    name: str
    topic: str
    msgtypes: tuple[str, ...]
    decode: Callable  # one deserialized message -> measurement
    landmark: bool = False  # the topic of a landmark kind
    batch: Callable | None = None  # a decoded block (fgslam.io.cdr_batch) -> (ns, measurements)
    parser: CdrParser | None = None  # raw CDR -> what ``decode`` takes (a landmark kind's fast path)


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


def _compression_hint(raw, bare: bool) -> str:
    """Why a message may not decode: rosbag2's per-message compression is recorded only in the
    bag's metadata.yaml, so a bare storage file hands out zstd frames instead of CDR."""
    directory = "give the bag as its directory, with metadata.yaml, not the bare .mcap/.db3 file"
    if bytes(raw[:4]) == ZSTD_MAGIC:
        if not bare:
            return ("; the message is zstd-compressed (a zstd frame: it starts 28 b5 2f fd), yet metadata.yaml "
                    "does not record per-message compression (compression_mode: message)")
        return ("; the message is zstd-compressed (a zstd frame: it starts 28 b5 2f fd): the bag was recorded "
                "with per-message compression (compression_mode: message), which only its metadata.yaml "
                f"records; {directory}")
    if bare:
        return f"; if the bag was recorded with per-message compression (compression_mode: message), {directory}"
    return ""


class OpenBag:
    """An open bag as fgslam reads it: rosbags' ``AnyReader`` (``reader``) with every message type
    name in its ROS 2 form (:func:`reloc.bag_spec.ros2_msgtype`): in ``topics`` (a topic whose
    connections differ only by the form of their type name has that one type) and in
    :meth:`deserialize`. :meth:`decode` turns a message that cannot be decoded into a
    :class:`BagError` naming the bag, the topic and the cause. ``connections`` and
    :meth:`messages` are rosbags' own (the type names as recorded)."""

    def __init__(self, reader, bag: Path, path: Path) -> None:
        self.reader, self.bag, self.path = reader, bag, path
        self.topics = {}
        for topic, info in reader.topics.items():
            types = {ros2_msgtype(c.msgtype) for c in info.connections}
            self.topics[topic] = info._replace(msgtype=types.pop() if len(types) == 1 else None)

    @property
    def connections(self) -> list:
        return self.reader.connections

    @property
    def start_time(self) -> int:
        return self.reader.start_time

    @property
    def end_time(self) -> int:
        return self.reader.end_time

    @property
    def typestore(self):
        """The message definitions of the bag (its own where it embeds them)."""
        return self.reader.typestore

    def messages(self, *args, **kwargs):
        """rosbags' ``AnyReader.messages``: (connection, log time ns, raw CDR bytes)."""
        return self.reader.messages(*args, **kwargs)

    def deserialize(self, raw, msgtype: str):
        """One message of type ``msgtype`` (either form of the name); rosbags' errors pass through."""
        return self.reader.deserialize(raw, ros2_msgtype(msgtype))

    def decode(self, conn, raw):
        """The message ``raw`` of connection ``conn``; one that cannot be decoded is a BagError."""
        try:
            return self.deserialize(raw, conn.msgtype)
        except Exception as exc:  # rosbags raises AnyReaderError, KeyError, struct/index errors, ...
            raise BagError(
                f"bag {self.path}: topic {conn.topic}: a message cannot be decoded "
                f"({type(exc).__name__}: {exc}){_compression_hint(raw, self.bag.is_file())}"
            ) from exc

    def close(self) -> None:
        self.reader.close()


def _hashed_ros1_names(exc: Exception, bag: Path, path: Path) -> BagError | None:
    """The error of a bag whose ROS 1-style type names come with RIHS01 type hashes: rosbags
    (0.11) looks the hash up under the recorded name, which its typestore holds only in the ROS 2
    form, and fails in ``AnyReader.open`` with a KeyError naming the type. None for other errors."""
    name = exc.args[0] if isinstance(exc, KeyError) and exc.args else None
    if not isinstance(name, str) or ros2_msgtype(name) == name:
        return None
    files = sorted(bag.glob("*.mcap")) + sorted(bag.glob("*.db3")) if bag.is_dir() else []
    alone = (f", or read its storage file {files[0]} alone (not for a bag recorded with per-message "
             "compression)" if len(files) == 1 else "")
    return BagError(
        f"bag {path} cannot be opened: its message type {name!r} has a ROS 1-style name (ROS 2: "
        f"{ros2_msgtype(name)!r}) and a type hash (type_description_hash in metadata.yaml), which rosbags, "
        "the library fgslam reads bags with, cannot match to the type; fgslam reads such names without "
        f"hashes: remove the type_description_hash entries from metadata.yaml{alone}"
    )


def _open(bag: Path, path: Path) -> OpenBag:
    """Open ``bag`` (resolved by :func:`_resolve` from ``path``, the path the user gave)."""
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([bag], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises many kinds on garbage input; all mean "not readable"
        if (named := _hashed_ros1_names(exc, bag, path)) is not None:
            raise named from exc
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
    return OpenBag(reader, bag, path)


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
        msgtype = info[r.topic].msgtype  # the ROS 2 form (OpenBag)
        if msgtype not in {ros2_msgtype(t) for t in r.msgtypes}:
            raise BagError(
                f"bag {path}: topic {r.topic} has type {msgtype or 'mixed'}, "
                f"expected {' or '.join(r.msgtypes)}"
            )
        selected[r.topic] = info[r.topic].connections
    return selected


def _probe(reader: OpenBag, topics: list[str]) -> None:
    """Decode the first message of each of ``topics`` found among the bag's first
    :data:`PROBE_MESSAGES` messages (one message per topic, once per source): a bag none of whose
    messages can be decoded (per-message compression read from the bare file, a type the
    definitions do not match) is refused here, naming the topic and the cause, before any pass.
    A chunk that cannot be read ends the probe; the pass reports it, with its position."""
    todo = set(topics)
    conns = [c for t in topics for c in reader.topics[t].connections]
    messages = reader.messages(connections=conns)
    try:
        for k, (conn, _, raw) in enumerate(messages):
            if conn.topic in todo:
                reader.decode(conn, raw)
                todo.discard(conn.topic)
            if not todo or k + 1 >= PROBE_MESSAGES:
                break
    except BagError:
        raise
    except Exception:  # a corrupt chunk: the pass names it, with its position, when it reads the bag
        log.debug("bag %s: probe ended at an unreadable message", reader.path, exc_info=True)
    finally:
        messages.close()


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
                           codec.decoder(ctx), landmark=True, parser=codec.parser))
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
            _probe(reader, self._topics)
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

"""Read a ROS 2 bag into one time-ordered stream of typed measurements.

The same path serves simulated bags (``sim.bag_writer``) and real recordings: any rosbag2
directory (MCAP or SQLite3 storage, with ``metadata.yaml``) or a bare ``.mcap`` / ``.db3`` file
holding the topics of :class:`~sim.rosmsgs.TopicNames`. Bags embed their message definitions;
for bags that do not, the Jazzy typestore with vision_msgs is the fallback.

Measurement time is the header stamp (integer ns -> float s), not the recording time; only an
unstamped ``geometry_msgs/Twist`` on the command topic falls back to the log time. Stamps are
checked per topic: messages older than an earlier one are counted as reordered and sorted (within
``BagReaderConfig.reorder_window_s``; older still, they are dropped as late); exact duplicates
(same stamp, same content) are dropped; same-stamp messages with different content keep the first
one recorded; messages with NaN/inf or otherwise invalid content are dropped.

The bag is streamed (:class:`BagSource`): a kilometre traverse is never held in memory, and
:func:`read_bag` is the same stream collected into a list.
Every such repair is counted in :class:`BagReport` and logged at WARNING. With
``repair=False`` each of them raises :class:`~fgslam.errors.BagError` instead.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fgslam.errors import BagError
from fgslam.io.bag_decode import (
    BagReaderConfig,
    DecodeError,
    RockDecoder,
    UnknownFrameError,
    decode_cmd_vel,
    decode_ground_truth,
    decode_imu,
    decode_wheel_odom,
    has_nonfinite,
    header_ns,
    same_measurement,
)
from fgslam.io.cdr_batch import (
    LAYOUTS,
    batch_cmd_vel,
    batch_ground_truth,
    batch_imu,
    batch_wheel_odom,
    decode_block,
    row_finite,
)
from reloc.errors import MeasurementError
from reloc.measurements import Measurement, sort_key
from sim.rosmsgs import (
    CMD_VEL_TYPE,
    CMD_VEL_UNSTAMPED_TYPE,
    IMU_TYPE,
    ODOMETRY_TYPE,
    ROCKS_TYPE,
    TopicNames,
    typestore,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TopicReport:
    """Per-topic counts: messages in the bag, measurements kept, and each kind of repair."""

    topic: str
    role: str
    msgtype: str
    n_messages: int = 0
    n_kept: int = 0
    n_reordered: int = 0  # stamp older than an earlier message on the topic (sorted)
    n_duplicates: int = 0  # same stamp and content as a kept message (dropped)
    n_conflicts: int = 0  # same stamp, different content (dropped; the first recorded is kept)
    n_nonfinite: int = 0  # NaN/inf in the message (dropped)
    n_invalid: int = 0  # other content that is no valid measurement (dropped)
    n_late: int = 0  # stamped more than the reorder window before a message recorded earlier (dropped)
    n_log_stamped: int = 0  # unstamped messages timed by the bag's log time
    first_problem: str = ""  # the first invalid message's problem, for the log

    @property
    def n_repairs(self) -> int:
        return (
            self.n_reordered
            + self.n_duplicates
            + self.n_conflicts
            + self.n_nonfinite
            + self.n_invalid
            + self.n_late
        )


@dataclass(frozen=True)
class BagReport:
    """What :func:`read_bag` found: ``topics`` maps topic name -> :class:`TopicReport`;
    ``repairs`` holds one human-readable line per repair kind applied."""

    path: Path
    topics: dict[str, TopicReport] = field(default_factory=dict)
    repairs: tuple[str, ...] = ()

    @property
    def n_repairs(self) -> int:
        return sum(r.n_repairs for r in self.topics.values())


@dataclass(frozen=True)
class BagStream:
    """A bag as measurements sorted by :func:`reloc.measurements.sort_key`, plus the read report."""

    measurements: list[Measurement]
    report: BagReport

    def of_type(self, cls: type) -> list:
        """The measurements of one type, in stream order."""
        return [m for m in self.measurements if type(m) is cls]


@dataclass(frozen=True)
class _Role:
    name: str
    topic: str
    msgtypes: tuple[str, ...]
    decode: Callable  # one deserialized message -> measurement
    batch: Callable | None = None  # a decoded block (fgslam.io.cdr_batch) -> (ns, measurement) rows


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


def _check_topics(reader, roles: list[_Role], path: Path) -> dict[str, object]:
    """Validate topic presence and types; return topic -> connections to read."""
    info = reader.topics
    present = {r.name: r.topic in info and info[r.topic].msgcount > 0 for r in roles}
    listing = (
        ", ".join(f"{t} ({i.msgtype}, {i.msgcount})" for t, i in sorted(info.items())) or "none"
    )
    by_name = {r.name: r for r in roles}
    missing = [by_name[n].topic for n in ("imu", "rocks") if not present[n]]
    if not (present["cmd_vel"] or present["wheel_odom"]):
        missing.append(f"{by_name['cmd_vel'].topic} or {by_name['wheel_odom'].topic}")
    if missing:
        raise BagError(
            f"bag {path}: required topic(s) missing or empty: {', '.join(missing)}; "
            f"topics present: {listing}"
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


def _roles(topics: TopicNames, rocks: RockDecoder) -> list[_Role]:
    return [
        _Role("cmd_vel", topics.cmd_vel, (CMD_VEL_TYPE, CMD_VEL_UNSTAMPED_TYPE), decode_cmd_vel, batch_cmd_vel),
        _Role("wheel_odom", topics.wheel_odom, (ODOMETRY_TYPE,), decode_wheel_odom, batch_wheel_odom),
        _Role("imu", topics.imu, (IMU_TYPE,), decode_imu, batch_imu),
        _Role("rocks", topics.rocks, (ROCKS_TYPE,), rocks),
        _Role("ground_truth", topics.ground_truth, (ODOMETRY_TYPE,), decode_ground_truth, batch_ground_truth),
    ]


class BagSource:
    """A bag as a lazily decoded, time-ordered measurement stream that can be iterated again.

    Each iteration opens the bag, decodes its messages in blocks of :data:`BLOCK` (the motion
    messages vectorised, :mod:`fgslam.io.cdr_batch`) and yields measurements in
    :func:`reloc.measurements.sort_key` order, holding only ``reorder_window_s`` of stream in
    memory: the repairs of the module doc are applied as the messages pass. A message stamped
    more than the window before the newest stamp recorded before it cannot be put in order any
    more; it is dropped and counted as late (``repair=False``: raised). The topics and their types are checked
    when the source is made; ``report`` is set after the first complete iteration (whose repairs
    are logged once), and a required topic none of whose messages was usable raises at its end.
    """

    def __init__(self, path: str | Path, topics: TopicNames | None = None, *,
                 camera_frames: dict[str, np.ndarray] | None = None, repair: bool = True,
                 config: BagReaderConfig | None = None) -> None:
        self.path = Path(path)
        self.config = config or BagReaderConfig()
        self.repair = repair
        self._roles = _roles(topics or TopicNames(), RockDecoder(self.config, camera_frames))  # checks extrinsics first
        self._bag = _resolve(self.path)
        reader = _open(self._bag, self.path)
        try:
            self._topics = list(_check_topics(reader, self._roles, self.path))
            self.message_counts = {t: int(reader.topics[t].msgcount) for t in self._topics}
            self._span_ns = (int(reader.start_time), int(reader.end_time))
        finally:
            reader.close()
        self.report: BagReport | None = None

    def __iter__(self) -> Iterator[Measurement]:
        return self._stream(self._roles)

    def ground_truth(self) -> list[Measurement]:
        """The ground-truth measurements only (reads just that topic; [] when the bag has none)."""
        return list(self._only(("ground_truth",)))

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
            merge = _Merge(roles, [r.topic for r in roles if r.topic in self._topics], reader,
                           self.path, self.repair, self.config.reorder_window_s)
            yield from merge.run()
        finally:
            reader.close()
        if check and roles is self._roles:
            reports = merge.reports()
            _check_kept(reports, self.path)
            if self.report is None:
                repairs = [line for r in reports.values() for line in _log_repairs(r, self.path)]
                self.report = BagReport(path=self.path, topics=reports, repairs=tuple(repairs))


def read_bag(
    path: str | Path,
    topics: TopicNames | None = None,
    *,
    camera_frames: dict[str, np.ndarray] | None = None,
    repair: bool = True,
    config: BagReaderConfig | None = None,
) -> BagStream:
    """Read the whole bag at ``path`` (rosbag2 directory or .mcap/.db3 file) into a
    :class:`BagStream` (a :class:`BagSource` iterated once into memory).

    ``camera_frames`` maps a detection frame id to ``T_base_cam`` (4, 4), so rocks reported in a
    camera frame are rotated and translated into base_link. Raises :class:`BagError` naming the
    bag, the topic and the problem on unreadable bags, missing required topics (imu, rocks, and
    cmd_vel or wheel_odom), wrong message types, unknown frames, and (``repair=False``) on any
    stamp or content problem that would otherwise be repaired.
    """
    source = BagSource(path, topics, camera_frames=camera_frames, repair=repair, config=config)
    measurements = list(source)
    log.info("read bag %s: %d measurements, %s", source.path, len(measurements),
             {t: r.n_kept for t, r in source.report.topics.items()})
    return BagStream(measurements, source.report)


BLOCK = 2048  # messages decoded at once (the vectorised decoders' batch)


class _Merge:
    """One pass over a bag: blocks of raw messages -> measurements -> per-topic stamp repairs ->
    one stream in sort_key order, released once no message still to come can precede it."""

    def __init__(self, roles, topics, reader, path: Path, repair: bool, window_s: float) -> None:
        self.role = {r.topic: r for r in roles if r.topic in topics}
        self.reader, self.path, self.repair = reader, path, repair
        self.window_ns = int(round(window_s * 1e9))
        self.counts = {t: {"msgtype": reader.topics[t].msgtype, "n_messages": 0, "n_kept": 0, "n_reordered": 0,
                           "n_duplicates": 0, "n_conflicts": 0, "n_nonfinite": 0, "n_invalid": 0, "n_late": 0,
                           "n_log_stamped": 0, "first_problem": ""} for t in self.role}
        self.raw: dict[str, list] = {t: [] for t in self.role}  # (arrival, log_ns, raw) waiting for decoding
        self.heap: list = []
        self.seq = 0
        self.max_ns = {t: None for t in self.role}  # latest stamp decoded per topic
        self.newest_ns = None  # latest stamp decoded on any topic
        self.group: dict[str, tuple[int, list]] = {}  # per topic: stamp and measurements released at it

    def run(self) -> Iterator[Measurement]:
        conns = [c for t in self.role for c in self.reader.topics[t].connections]
        topic, n_raw = None, 0
        try:
            for conn, log_ns, raw in self.reader.messages(connections=conns):
                topic = conn.topic
                self.counts[topic]["n_messages"] += 1
                self.raw[topic].append((n_raw, log_ns, raw))
                n_raw += 1
                if n_raw >= BLOCK:
                    self._decode_buffered()
                    n_raw = 0
                    yield from self._release(final=False)
        except BagError:
            raise
        except Exception as exc:  # a corrupt chunk or record surfaces as any of rosbags' errors
            where = f"after a message on topic {topic}" if topic else "before the first message"
            raise BagError(f"bag {self.path}: reading failed {where} (truncated or corrupt bag): "
                           f"{type(exc).__name__}: {exc}") from exc
        self._decode_buffered()
        yield from self._release(final=True)

    def reports(self) -> dict[str, TopicReport]:
        return {t: TopicReport(topic=t, role=self.role[t].name, **c) for t, c in self.counts.items()}

    def _decode_buffered(self) -> None:
        """Decode the buffered messages topic by topic, then take them in recording order."""
        decoded = []
        for topic, items in self.raw.items():
            if items:
                decoded += self._decode(topic, items)
                self.raw[topic] = []
        decoded.sort(key=lambda d: d[0])
        for _, topic, ns, m, n, nonfinite in decoded:
            self._decoded(topic, ns, m, n, nonfinite)

    def _decode(self, topic: str, items: list) -> list[tuple]:
        """(arrival, topic, ns, measurement or its error, message number, nonfinite) per message."""
        role, counts = self.role[topic], self.counts[topic]
        msgtype = counts["msgtype"]
        n0 = counts["n_messages"] - len(items) + 1
        block = decode_block([raw for _, _, raw in items], LAYOUTS[msgtype]) if role.batch and msgtype in LAYOUTS else None
        if block is not None:
            if block.stamp_ns is None:
                counts["n_log_stamped"] += len(items)
            stamps, built = role.batch(block, [ln for _, ln, _ in items])
            return [(a, topic, ns, m, n0 + k, not ok) for k, ((a, _, _), ns, m, ok)
                    in enumerate(zip(items, stamps.tolist(), built, row_finite(block).tolist()))]
        out = []
        for k, (arrival, log_ns, raw) in enumerate(items):
            try:
                msg = self.reader.deserialize(raw, msgtype)
            except Exception as exc:
                raise BagError(f"bag {self.path}: topic {topic}: message {n0 + k} cannot be deserialized "
                               f"(corrupt bag): {type(exc).__name__}: {exc}") from exc
            if hasattr(msg, "header"):
                ns = header_ns(msg.header)
            else:
                ns = int(log_ns)
                counts["n_log_stamped"] += 1
            try:
                m = role.decode(msg, ns)
            except UnknownFrameError as exc:
                raise BagError(f"bag {self.path}: topic {topic}: {exc}") from None
            except (MeasurementError, DecodeError) as exc:
                m = exc
            out.append((arrival, topic, ns, m, n0 + k, isinstance(m, Exception) and has_nonfinite(msg)))
        return out

    def _decoded(self, topic: str, ns: int, m, n: int, nonfinite: bool) -> None:
        counts = self.counts[topic]
        if isinstance(m, Exception):
            if not self.repair:
                raise BagError(f"bag {self.path}: topic {topic}: message {n} (stamp {ns} ns) is invalid: {m}")
            counts["n_nonfinite" if nonfinite else "n_invalid"] += 1
            counts["first_problem"] = counts["first_problem"] or str(m)
            return
        latest = self.max_ns[topic]
        if latest is not None and ns < latest:
            if not self.repair:
                raise BagError(f"bag {self.path}: topic {topic}: message {n} stamped earlier than a message "
                               "recorded before it (out of order)")
            if self.newest_ns - ns > self.window_ns:  # too late to be put in order: it may follow released ones
                counts["n_late"] += 1
                return
            counts["n_reordered"] += 1
        elif self.newest_ns is not None and self.newest_ns - ns > self.window_ns:
            if not self.repair:
                raise BagError(f"bag {self.path}: topic {topic}: message {n} stamped {ns} ns, more than "
                               f"{self.window_ns / 1e9:g} s before messages recorded earlier (out of order)")
            counts["n_late"] += 1
            return
        self.max_ns[topic] = ns if latest is None else max(latest, ns)
        self.newest_ns = ns if self.newest_ns is None else max(self.newest_ns, ns)
        self.seq += 1
        heapq.heappush(self.heap, (sort_key(m), ns, self.seq, topic, m))

    def _release(self, final: bool) -> Iterator[Measurement]:
        horizon = None if final or self.newest_ns is None else self.newest_ns - self.window_ns
        heap = self.heap
        while heap and (horizon is None or heap[0][1] <= horizon):
            key, ns, _, topic, m = heapq.heappop(heap)
            counts = self.counts[topic]
            g_ns, g = self.group.get(topic, (None, []))
            if ns == g_ns:
                dup = any(same_measurement(m, k) for k in g)
                if not self.repair:
                    raise BagError(f"bag {self.path}: topic {topic}: a message shares its stamp {ns} ns with an "
                                   f"earlier one ({'duplicate' if dup else 'conflicting'})")
                counts["n_duplicates" if dup else "n_conflicts"] += 1
                continue
            self.group[topic] = (ns, [m])
            counts["n_kept"] += 1
            yield m


_REPAIR_TEXT = {
    "n_reordered": "sorted %d message(s) recorded out of stamp order",
    "n_duplicates": "dropped %d exact duplicate message(s)",
    "n_conflicts": "dropped %d message(s) sharing a stamp with different content "
    "(kept the first recorded)",
    "n_nonfinite": "dropped %d message(s) holding NaN/inf",
    "n_invalid": "dropped %d invalid message(s)",
    "n_late": "dropped %d message(s) stamped more than the reorder window before earlier-recorded ones",
}


def _check_kept(reports: dict[str, TopicReport], path: Path) -> None:
    """A required input whose every message was dropped is an error, not an empty stream."""
    by_role = {r.role: r for r in reports.values()}
    motion = [by_role[k] for k in ("cmd_vel", "wheel_odom") if k in by_role]
    needed = [by_role["imu"], by_role["rocks"]]
    if not any(r.n_kept for r in motion):
        needed += motion
    for r in needed:
        if r.n_kept == 0:
            raise BagError(
                f"bag {path}: topic {r.topic}: none of its {r.n_messages} message(s) is usable"
                + (f" (first problem: {r.first_problem})" if r.first_problem else "")
            )


def _log_repairs(report: TopicReport, path: Path) -> list[str]:
    lines = []
    for name, text in _REPAIR_TEXT.items():
        n = getattr(report, name)
        if n:
            line = f"{report.topic}: " + text % n
            if name in ("n_invalid", "n_nonfinite") and report.first_problem:
                line += f" (first: {report.first_problem})"
            log.warning("bag %s: %s", path, line)
            lines.append(line)
    if report.n_log_stamped:
        log.info(
            "bag %s: %s: %d unstamped message(s) timed by the log time",
            path,
            report.topic,
            report.n_log_stamped,
        )
    return lines

"""Read a ROS 2 bag into one time-ordered stream of typed measurements.

The same path serves simulated bags (``sim.bag_writer``) and real recordings: any rosbag2
directory (MCAP or SQLite3 storage, with ``metadata.yaml``) or a bare ``.mcap`` / ``.db3`` file
holding the topics of :class:`~sim.rosmsgs.TopicNames`. Bags embed their message definitions;
for bags that do not, the Jazzy typestore with vision_msgs is the fallback.

Measurement time is the header stamp (integer ns -> float s), not the recording time; only an
unstamped ``geometry_msgs/Twist`` on the command topic falls back to the log time. Stamps are
checked per topic: messages older than an earlier one are counted as reordered and sorted; exact
duplicates (same stamp, same content) are dropped; same-stamp messages with different content
keep the first one recorded; messages with NaN/inf or otherwise invalid content are dropped.
Every such repair is counted in :class:`BagReport` and logged at WARNING. With
``repair=False`` each of them raises :class:`~fgslam.errors.BagError` instead.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
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
    decode: Callable


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


def read_bag(
    path: str | Path,
    topics: TopicNames | None = None,
    *,
    camera_frames: dict[str, np.ndarray] | None = None,
    repair: bool = True,
    config: BagReaderConfig | None = None,
) -> BagStream:
    """Read the bag at ``path`` (rosbag2 directory or .mcap/.db3 file) into a :class:`BagStream`.

    ``camera_frames`` maps a detection frame id to ``T_base_cam`` (4, 4), so rocks reported in a
    camera frame are rotated and translated into base_link. Raises :class:`BagError` naming the
    bag, the topic and the problem on unreadable bags, missing required topics (imu, rocks, and
    cmd_vel or wheel_odom), wrong message types, unknown frames, and (``repair=False``) on any
    stamp or content problem that would otherwise be repaired.
    """
    path = Path(path)
    topics = topics or TopicNames()
    config = config or BagReaderConfig()
    rocks = RockDecoder(config, camera_frames)  # validates the extrinsics before any I/O
    roles = [
        _Role("cmd_vel", topics.cmd_vel, (CMD_VEL_TYPE, CMD_VEL_UNSTAMPED_TYPE), decode_cmd_vel),
        _Role("wheel_odom", topics.wheel_odom, (ODOMETRY_TYPE,), decode_wheel_odom),
        _Role("imu", topics.imu, (IMU_TYPE,), decode_imu),
        _Role("rocks", topics.rocks, (ROCKS_TYPE,), rocks),
        _Role("ground_truth", topics.ground_truth, (ODOMETRY_TYPE,), decode_ground_truth),
    ]
    reader = _open(_resolve(path), path)
    try:
        selected = _check_topics(reader, roles, path)
        per_topic = _decode_all(reader, selected, roles, path, repair)
    finally:
        reader.close()

    measurements: list[Measurement] = []
    reports: dict[str, TopicReport] = {}
    repairs: list[str] = []
    for role in roles:
        if role.topic not in per_topic:
            continue
        entries, counts = per_topic[role.topic]
        kept, counts = _repair_stamps(entries, counts, role.topic, path, repair)
        measurements.extend(kept)
        report = TopicReport(topic=role.topic, role=role.name, n_kept=len(kept), **counts)
        reports[role.topic] = report
        repairs.extend(_log_repairs(report, path))
    _check_kept(reports, path)
    measurements.sort(key=sort_key)
    log.info(
        "read bag %s: %d measurements, %s",
        path,
        len(measurements),
        {t: r.n_kept for t, r in reports.items()},
    )
    return BagStream(measurements, BagReport(path=path, topics=reports, repairs=tuple(repairs)))


def _decode_all(reader, selected, roles: list[_Role], path: Path, repair: bool):
    """Deserialize and decode every selected message: topic -> ([(ns, seq, m)], counts)."""
    role_of = {r.topic: r for r in roles}
    out: dict[str, tuple[list, dict]] = {
        t: (
            [],
            {
                "msgtype": reader.topics[t].msgtype,
                "n_messages": 0,
                "n_nonfinite": 0,
                "n_invalid": 0,
                "n_log_stamped": 0,
                "first_problem": "",
            },
        )
        for t in selected
    }
    connections = [c for conns in selected.values() for c in conns]
    topic = None
    seq = 0
    try:
        for conn, log_ns, raw in reader.messages(connections=connections):
            topic = conn.topic
            entries, counts = out[topic]
            counts["n_messages"] += 1
            seq += 1
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise BagError(
                    f"bag {path}: topic {topic}: message {counts['n_messages']} cannot be "
                    f"deserialized (corrupt bag): {type(exc).__name__}: {exc}"
                ) from exc
            if hasattr(msg, "header"):
                ns = header_ns(msg.header)
            else:
                ns = int(log_ns)
                counts["n_log_stamped"] += 1
            try:
                m = role_of[topic].decode(msg, ns)
            except UnknownFrameError as exc:
                raise BagError(f"bag {path}: topic {topic}: {exc}") from None
            except (MeasurementError, DecodeError) as exc:
                kind = "n_nonfinite" if has_nonfinite(msg) else "n_invalid"
                if not repair:
                    raise BagError(
                        f"bag {path}: topic {topic}: message {counts['n_messages']} "
                        f"(stamp {ns} ns) is invalid: {exc}"
                    ) from None
                counts[kind] += 1
                counts["first_problem"] = counts["first_problem"] or str(exc)
                continue
            entries.append((ns, seq, m))
    except BagError:
        raise
    except Exception as exc:  # a corrupt chunk or record surfaces as any of rosbags' errors
        where = f"after a message on topic {topic}" if topic else "before the first message"
        raise BagError(
            f"bag {path}: reading failed {where} (truncated or corrupt bag): "
            f"{type(exc).__name__}: {exc}"
        ) from exc
    return out


def _repair_stamps(entries: list, counts: dict, topic: str, path: Path, repair: bool):
    """Sort one topic by stamp and drop same-stamp repeats; return (measurements, counts)."""
    n_reordered = 0
    latest = None
    for ns, _, _ in entries:
        if latest is not None and ns < latest:
            n_reordered += 1
        latest = ns if latest is None else max(latest, ns)
    if n_reordered and not repair:
        raise BagError(
            f"bag {path}: topic {topic}: {n_reordered} message(s) stamped earlier than "
            "a message recorded before them (out of order)"
        )
    entries = sorted(entries, key=lambda e: (e[0], e[1]))
    kept: list[Measurement] = []
    n_dup = n_conflict = 0
    group_ns, group = None, []
    for ns, _, m in entries:
        if ns != group_ns:
            group_ns, group = ns, []
        if not group:
            group.append(m)
            kept.append(m)
        elif any(same_measurement(m, k) for k in group):
            n_dup += 1
        else:
            n_conflict += 1
    if (n_dup or n_conflict) and not repair:
        raise BagError(
            f"bag {path}: topic {topic}: {n_dup} duplicate and {n_conflict} conflicting "
            "message(s) share a stamp with an earlier one"
        )
    return kept, dict(counts, n_reordered=n_reordered, n_duplicates=n_dup, n_conflicts=n_conflict)


_REPAIR_TEXT = {
    "n_reordered": "sorted %d message(s) recorded out of stamp order",
    "n_duplicates": "dropped %d exact duplicate message(s)",
    "n_conflicts": "dropped %d message(s) sharing a stamp with different content "
    "(kept the first recorded)",
    "n_nonfinite": "dropped %d message(s) holding NaN/inf",
    "n_invalid": "dropped %d invalid message(s)",
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

"""Read a ROS 2 bag into one time-ordered stream of typed measurements.

The same path serves simulated bags (``sim.bag_writer``) and real recordings: any rosbag2
directory (MCAP or SQLite3 storage, with ``metadata.yaml``) or a bare ``.mcap`` / ``.db3`` file
holding the topics of :class:`~reloc.bag_spec.TopicNames`. Motion inputs and ground truth have
fixed roles; every registered landmark kind with a bag layer (:mod:`reloc.kinds`) is one more
role, decoded by its codec. Bags embed their message definitions; for bags that do not, the
Jazzy typestore with vision_msgs is the fallback.

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
from collections.abc import Callable, Sequence
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
    has_nonfinite,
    header_ns,
)
from fgslam.io.bag_report import (
    BagReport,
    BagStream,
    TopicReport,
    check_kept,
    log_repairs,
    repair_stamps,
)
from reloc.bag_spec import (
    CMD_VEL_TYPE,
    CMD_VEL_UNSTAMPED_TYPE,
    IMU_TYPE,
    ODOMETRY_TYPE,
    BagCodecError,
    DecodeContext,
    MessageContentError,
    TopicNames,
    UnknownFrameError,
    check_transform,
    typestore,
)
from reloc.errors import MeasurementError
from reloc.kinds import UnknownKindError, kind_named, kinds_with
from reloc.measurements import Measurement, sort_key

log = logging.getLogger(__name__)

__all__ = ["BagReport", "BagStream", "TopicReport", "read_bag"]


@dataclass(frozen=True)
class _Role:
    name: str
    topic: str
    msgtypes: tuple[str, ...]
    decode: Callable
    landmark: bool = False  # the topic of a landmark kind


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
    missing = [by_name["imu"].topic] if not present["imu"] else []
    landmarks = [r for r in roles if r.landmark]
    if not any(present[r.name] for r in landmarks):  # at least one landmark kind
        missing.append(" or ".join(r.topic for r in landmarks) or "a landmark topic (no kind selected)")
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


def read_bag(
    path: str | Path,
    topics: TopicNames | None = None,
    *,
    camera_frames: dict[str, np.ndarray] | None = None,
    repair: bool = True,
    config: BagReaderConfig | None = None,
    kinds: Sequence[str] | None = None,
) -> BagStream:
    """Read the bag at ``path`` (rosbag2 directory or .mcap/.db3 file) into a :class:`BagStream`.

    ``camera_frames`` maps a detection frame id to ``T_base_cam`` (4, 4), so landmarks reported
    in a camera frame are rotated and translated into base_link. ``kinds`` names the landmark
    kinds to read (default: every registered kind with a bag layer). Raises :class:`BagError`
    naming the bag, the topic and the problem on unreadable bags, missing required topics (imu,
    cmd_vel or wheel_odom, and a landmark topic), wrong message types, unknown frames, unknown
    kinds, and (``repair=False``) on any stamp or content problem that would otherwise be repaired.
    """
    path = Path(path)
    topics = topics or TopicNames()
    config = config or BagReaderConfig()
    ctx = DecodeContext(config, _frames(config, camera_frames))  # extrinsics checked before any I/O
    roles = [
        _Role("cmd_vel", topics.cmd_vel, (CMD_VEL_TYPE, CMD_VEL_UNSTAMPED_TYPE), decode_cmd_vel),
        _Role("wheel_odom", topics.wheel_odom, (ODOMETRY_TYPE,), decode_wheel_odom),
        _Role("imu", topics.imu, (IMU_TYPE,), decode_imu),
        *_landmark_roles(topics, kinds, ctx),
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
        kept, counts = repair_stamps(entries, counts, role.topic, path, repair)
        measurements.extend(kept)
        report = TopicReport(topic=role.topic, role=role.name, n_kept=len(kept), **counts)
        reports[role.topic] = report
        repairs.extend(log_repairs(report, path))
    check_kept(reports, {r.name for r in roles if r.landmark}, path)
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
            except (MeasurementError, MessageContentError) as exc:
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

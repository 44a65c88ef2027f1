"""What reading a bag found and repaired: per-topic counts (:class:`TopicReport`), the whole
bag's report (:class:`BagReport`), the stream (:class:`BagStream`), the repair lines logged and
the check that every required topic kept a message (the repairs themselves are applied as the
stream passes, :class:`fgslam.io.bag_reader.BagSource`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from fgslam.errors import BagError
from reloc.measurements import Measurement

log = logging.getLogger("fgslam.io.bag_reader")


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


_REPAIR_TEXT = {
    "n_reordered": "sorted %d message(s) recorded out of stamp order",
    "n_duplicates": "dropped %d exact duplicate message(s)",
    "n_conflicts": "dropped %d message(s) sharing a stamp with different content "
    "(kept the first recorded)",
    "n_nonfinite": "dropped %d message(s) holding NaN/inf",
    "n_invalid": "dropped %d invalid message(s)",
    "n_late": "dropped %d message(s) stamped more than the reorder window before earlier-recorded ones",
}


def log_repairs(report: TopicReport, path: Path) -> list[str]:
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


def check_kept(reports: dict[str, TopicReport], landmark_roles: set[str], path: Path) -> None:
    """A required input whose every message was dropped is an error, not an empty stream: the
    IMU, every landmark topic present, and the motion input when no motion message is usable."""
    by_role = {r.role: r for r in reports.values()}
    motion = [by_role[k] for k in ("cmd_vel", "wheel_odom") if k in by_role]
    needed = [by_role["imu"]] + [r for r in reports.values() if r.role in landmark_roles]
    if not any(r.n_kept for r in motion):
        needed += motion
    for r in needed:
        if r.n_kept == 0:
            raise BagError(
                f"bag {path}: topic {r.topic}: none of its {r.n_messages} message(s) is usable"
                + (f" (first problem: {r.first_problem})" if r.first_problem else "")
            )

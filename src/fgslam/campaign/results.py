"""The campaign's results file, ``OUT/results.jsonl``: one task record per line, appended (and
flushed to disk) as each task completes, so an interrupted campaign keeps everything it finished.

Reading tolerates a torn last line (an interrupted write): it is skipped with a warning and the
next append starts on a fresh line. When a task appears more than once (a retried failure, a
rerun), its latest record counts.
"""

from __future__ import annotations

import json
import logging
import math
import numbers
import os
from pathlib import Path

from fgslam.campaign.spec import CampaignError

log = logging.getLogger(__name__)

RESULTS_NAME = "results.jsonl"


def identity(record: dict) -> tuple[str, str]:
    """(task key, config hash): two records with the same identity are the same computation."""
    return str(record.get("key")), str(record.get("config_hash"))


def read_records(path: Path) -> list[dict]:
    """Every well-formed record of a JSONL results file, in file order ([] when absent)."""
    path = Path(path)
    if not path.exists():
        return []
    records = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                log.warning("%s:%d: skipping a malformed line (an interrupted write?)", path, lineno)
                continue
            if not isinstance(rec, dict) or "key" not in rec or "status" not in rec:
                log.warning("%s:%d: skipping a line that is not a task record", path, lineno)
                continue
            records.append(rec)
    return records


def latest(records: list[dict]) -> dict[tuple[str, str], dict]:
    """Latest record per identity (see :func:`identity`)."""
    out: dict[tuple[str, str], dict] = {}
    for rec in records:
        out[identity(rec)] = rec
    return out


class ResultStore:
    """Append-only JSONL file of task records in a campaign's output directory."""

    def __init__(self, out_dir: Path) -> None:
        self.path = Path(out_dir) / RESULTS_NAME
        if self.path.exists() and not self.path.is_file():
            raise CampaignError(f"{self.path}: exists and is not a file")

    def records(self) -> list[dict]:
        """All readable records, in completion order."""
        return read_records(self.path)

    def done(self) -> set[tuple[str, str]]:
        """Identities whose latest record succeeded (a resumed campaign skips these)."""
        return {ident for ident, rec in latest(self.records()).items() if rec.get("status") == "ok"}

    def append(self, record: dict) -> None:
        """Write one record as a line and force it to disk."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        needs_newline = self.path.exists() and self.path.stat().st_size > 0 and not _ends_with_newline(self.path)
        line = json.dumps(clean(record), sort_keys=True, allow_nan=False)
        with self.path.open("a") as fh:
            if needs_newline:
                fh.write("\n")
            fh.write(line + "\n")
            fh.flush()
            os.fsync(fh.fileno())


def clean(o):
    """``o`` with non-finite floats as None, tuples as lists and numpy scalars as Python numbers (strict JSON)."""
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    if o is None or isinstance(o, (bool, str)):
        return o
    if type(o).__module__ == "numpy" and hasattr(o, "item"):  # numpy scalars, np.bool_ included
        return clean(o.item())
    if isinstance(o, numbers.Integral):
        return int(o)
    if isinstance(o, numbers.Real):
        return float(o) if math.isfinite(float(o)) else None
    return str(o)


def _ends_with_newline(path: Path) -> bool:
    with path.open("rb") as fh:
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) == b"\n"

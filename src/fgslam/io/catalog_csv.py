"""Orbital rock catalogs as CSV: header ``x,y,size,score`` (metres, world frame, size = diameter).

The ``score`` column is optional on read (a catalog without detector confidences gets 1.0 for
every rock). Any malformed content raises :class:`~fgslam.errors.InputFileError` naming the file,
the line and the problem, so a bad catalog never reaches the matcher half-read.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.errors import InputFileError
from reloc.errors import MeasurementError
from reloc.measurements import RockCatalog

log = logging.getLogger(__name__)

HEADER: tuple[str, ...] = ("x", "y", "size", "score")
MIN_CATALOG_ROCKS = 3  # the fewest rocks a catalog can be matched against (one triangle)
DUPLICATE_TOL_M = 1e-3  # two rows closer than this describe one rock twice
REQUIRED: tuple[str, ...] = ("x", "y", "size")


def read_catalog_csv(path: str | Path) -> RockCatalog:
    """Read a catalog CSV into a :class:`RockCatalog` (``xy_m`` (N, 2) world metres, ``size_m`` (N,)
    diameters, ``score`` (N,)). Extra columns are ignored; column order is free."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputFileError(f"cannot read catalog {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputFileError(f"catalog {path} is not UTF-8 text: {exc}") from exc
    rows = list(csv.reader(text.splitlines()))
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise InputFileError(
            f"catalog {path}: line 1: empty file, expected header 'x,y,size,score'"
        )
    header = [cell.strip().lower() for cell in rows[0]]
    dup = sorted({h for h in header if header.count(h) > 1 and h})
    if dup:
        raise InputFileError(f"catalog {path}: line 1: duplicate column(s) {', '.join(dup)}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputFileError(
            f"catalog {path}: line 1: missing column(s) {', '.join(missing)} "
            f"(header is {','.join(header)!r}, expected 'x,y,size,score')"
        )
    columns = [c for c in HEADER if c in header]
    index = {c: header.index(c) for c in columns}
    values: list[list[float]] = []
    linenos: list[int] = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not cell.strip() for cell in row):
            continue  # blank lines (e.g. a trailing newline) carry no rock
        if len(row) != len(header):
            raise InputFileError(
                f"catalog {path}: line {lineno}: {len(row)} field(s), header has {len(header)}"
            )
        parsed = []
        for c in columns:
            cell = row[index[c]].strip()
            try:
                v = float(cell)
            except ValueError:
                raise InputFileError(
                    f"catalog {path}: line {lineno}: column {c!r} is not a number: {cell!r}"
                ) from None
            if not math.isfinite(v):
                raise InputFileError(f"catalog {path}: line {lineno}: column {c!r} is {cell}")
            if c == "size" and v <= 0.0:
                raise InputFileError(
                    f"catalog {path}: line {lineno}: size must be a positive diameter, got {cell}"
                )
            parsed.append(v)
        values.append(parsed)
        linenos.append(lineno)
    if not values:
        raise InputFileError(f"catalog {path}: no rocks after the header")
    arr = np.asarray(values, dtype=float)
    _check_duplicates(path, arr[:, :2], linenos)
    score = arr[:, columns.index("score")] if "score" in columns else np.ones(len(arr))
    try:
        catalog = RockCatalog(xy_m=arr[:, [0, 1]], size_m=arr[:, 2], score=score)
    except MeasurementError as exc:  # pragma: no cover - the checks above catch these first
        raise InputFileError(f"catalog {path}: {exc}") from exc
    log.debug("read %d catalog rocks from %s", len(catalog), path)
    return catalog


def _check_duplicates(path: Path, xy_m: np.ndarray, linenos: list[int]) -> None:
    """Two rows at one position (within DUPLICATE_TOL_M) are one rock listed twice: a malformed
    catalog (a concatenated or re-exported file), never two rocks."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(xy_m).query_pairs(DUPLICATE_TOL_M, output_type="ndarray")
    if len(pairs):
        i, j = min(pairs.tolist())
        n = len(np.unique(pairs[:, 1]))
        raise InputFileError(
            f"catalog {path}: line {linenos[j]}: rock at ({xy_m[j, 0]:g}, {xy_m[j, 1]:g}) repeats line {linenos[i]} "
            f"({n} duplicate row(s) in all); remove the duplicates")


def write_catalog_csv(path: str | Path, catalog: RockCatalog) -> None:
    """Write ``catalog`` as CSV with header ``x,y,size,score`` (world metres, diameters, scores).

    Floats are written with ``repr`` precision so that a read-back is bit-exact.
    """
    path = Path(path)
    try:
        with path.open("w", encoding="utf-8", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(HEADER)
            for (x, y), d, s in zip(catalog.xy_m, catalog.size_m, catalog.score):
                w.writerow((repr(float(x)), repr(float(y)), repr(float(d)), repr(float(s))))
    except OSError as exc:
        raise InputFileError(f"cannot write catalog {path}: {exc.strerror or exc}") from exc


@dataclass(frozen=True)
class CatalogFile:
    """A landmark kind's catalog layer: its file name in a ``fgslam sim`` directory and its reader
    (``path -> catalog``)."""

    file_name: str
    read: Callable[[Path], object]


ROCK_CATALOG_FILE = CatalogFile("catalog.csv", read_catalog_csv)  # the rock kind's catalog layer

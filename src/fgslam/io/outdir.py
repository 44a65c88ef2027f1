"""Output directories written whole: checked before any work, locked, staged, then committed.

``OUT/manifest.json`` states what a directory is (``kind``: run, compare, sim, campaign, bench),
whether it is ``complete``, the command that wrote it and every file with its size and SHA-256.

    with OutputDir(out, "compare") as od:   # path checked, OUT created and locked, before any work
        ...                                 # the long computation
        write_comparison(od.staging, ...)   # files go to OUT/.staging-<pid>-*/
        files = od.commit()                 # the new files move in, stale ones go, manifest last

An interrupted run (an exception, Ctrl-C, SIGTERM) leaves OUT as it was, the previous result
complete and untouched; a killed one also leaves its staging directory, which the next run
removes. The commit itself first marks the manifest ``writing``, renames each file into place
(atomic per file), removes the files of the previous result that the new one does not have
(``--no-rrd`` leaves no old ``compare.rrd``), and only then writes the ``complete`` manifest.
Files fgslam did not write are never removed: a non-empty directory without a manifest (one
fgslam did not create) is refused unless ``force`` (``--force``: then its files of this kind are
replaced and the others kept), as is one holding another kind of output. The lock is an advisory ``flock`` on the
directory itself: a second fgslam on the same OUT stops at once with an error instead of
interleaving its files with the first one's.
"""

from __future__ import annotations

import contextlib
import datetime
import fnmatch
import hashlib
import json
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Self

from fgslam.errors import FgslamError

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
STAGING_PREFIX = ".staging-"
COMPLETE, WRITING, INCOMPLETE = "complete", "writing", "incomplete"
# what each kind of output holds: how the files of a directory written before manifests existed
# are told from files fgslam did not write
KNOWN_NAMES: dict[str, tuple[str, ...]] = {
    "run": ("*.tum", "metrics.json", "fixes.csv", "config.yaml", "*.rrd"),
    "compare": ("table.md", "results.json", "config.yaml", "compare.rrd", "*_xy.png", "*_errors.png",
                "*_fix_errors.png"),
    "sim": ("bag", "catalog.csv", "rocks_true.csv", "world.yaml", "orbital.png"),
    "campaign": ("results.jsonl", "summary.md", "summary.json", "campaign.json"),
    "bench": ("results.json", "table.md"),
}


class OutputDirError(FgslamError):
    """An output path is unusable (a file, not writable), locked, or holds files it must not lose."""


def _utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def check_output_path(path: Path, option: str = "--out", directory: bool = True) -> Path:
    """``path`` made absolute, if it can be written: an existing directory (or, ``directory``
    False, a file) or a new one whose nearest existing ancestor is a writable directory."""
    path = Path(path).expanduser().absolute()
    what = "directory" if directory else "file"
    if path.exists():
        if directory and not path.is_dir():
            raise OutputDirError(f"{option} {path}: exists and is not a directory")
        if not directory and path.is_dir():
            raise OutputDirError(f"{option} {path}: is a directory, expected a file")
    parent = path if directory and path.is_dir() else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputDirError(f"{option} {path}: cannot create the {what}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputDirError(f"{option} {path}: cannot write the {what}: {parent} is not writable")
    return path


@contextlib.contextmanager
def atomic_path(path: Path, option: str = "--out") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write; on success it replaces ``path`` at once
    (a reader sees the old file or the new one, never half of one), on failure it is removed."""
    path = check_output_path(path, option, directory=False)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputDirError(f"{option} {path}: cannot create {path.parent}: {exc.strerror or exc}") from None
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_text_atomic(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_path`); returns ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def read_manifest(directory: Path) -> dict | None:
    """The manifest of ``directory`` (None when it has none)."""
    p = Path(directory) / MANIFEST
    if not p.exists():
        return None
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise OutputDirError(f"{p}: unreadable manifest ({exc})") from None
    if not isinstance(data, dict) or "kind" not in data or "status" not in data:
        raise OutputDirError(f"{p}: not an fgslam manifest")
    return data


def require_complete(directory: Path, kind: str) -> dict | None:
    """The manifest of a directory about to be read as a ``kind`` output: an error when it says the
    directory is another kind or was not completely written. None for a directory without one."""
    m = read_manifest(directory)
    if m is None:
        return None
    if m["kind"] != kind:
        raise OutputDirError(f"{directory}: a `fgslam {m['kind']}` output, not a `fgslam {kind}` one")
    if m["status"] != COMPLETE:
        raise OutputDirError(f"{directory}: an incomplete `fgslam {kind}` output (status {m['status']!r}: "
                             f"interrupted while being written); write it again")
    return m


def _known(kind: str, name: str) -> bool:
    return any(fnmatch.fnmatch(name, pat) for pat in KNOWN_NAMES.get(kind, ()))


def _listing(root: Path, names) -> dict[str, dict]:
    """Every file of the top-level entries ``names`` of ``root``: relative path -> bytes, sha256."""
    out = {}
    entries = [root / n for n in sorted(names)]
    for p in [q for e in entries for q in ([e] if e.is_file() else sorted(e.rglob("*")))]:
        rel = p.relative_to(root).as_posix()
        if not p.is_file():
            continue
        h = hashlib.sha256()
        with p.open("rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        out[rel] = {"bytes": p.stat().st_size, "sha256": h.hexdigest()}
    return out


class OutputDir:
    """One output directory of kind ``kind`` (see module doc). ``replace`` False refuses to replace
    an earlier output (its files of this kind); ``staged`` False (an append-only campaign) writes in
    place and only keeps the lock and the manifest."""

    def __init__(self, path: Path, kind: str, *, replace: bool = True, staged: bool = True,
                 option: str = "--out", replace_hint: str = "", force: bool = False) -> None:
        self.path = Path(path).expanduser().absolute()
        self.kind, self.replace, self.staged, self.option = kind, replace, staged, option
        self.force = force
        self.replace_hint = replace_hint
        self.staging: Path = self.path
        self._fd: int | None = None
        self._created = False
        self._committed = False
        self._started = _utc_now()
        self._previous: dict | None = None

    # -- entering: path, lock, what is there -----------------------------------------------------
    def __enter__(self) -> Self:
        check_output_path(self.path, self.option)
        self._created = not self.path.exists()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._lock()
            self._inspect()
            if self.staged:
                self.staging = Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=self.path))
        except OSError as exc:
            self._release()
            raise OutputDirError(f"{self.option} {self.path}: cannot write there: {exc.strerror or exc}") from None
        except BaseException:
            self._release()
            raise
        return self

    def _lock(self) -> None:
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not Linux/macOS
            log.warning("no advisory locking on this platform: do not write %s from two processes", self.path)
            return
        self._fd = os.open(self.path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise OutputDirError(f"{self.option} {self.path}: another fgslam process is writing this directory "
                                 "(it is locked); wait for it or choose another directory") from None

    def _inspect(self) -> None:
        """Remove dead runs' staging; refuse what must not be replaced or mixed."""
        for p in self.path.glob(f"{STAGING_PREFIX}*"):
            if p.is_dir():
                log.info("removing %s, left by an interrupted run", p)
                shutil.rmtree(p, ignore_errors=True)
        self._previous = read_manifest(self.path)
        names = sorted(p.name for p in self.path.iterdir() if p.name != MANIFEST and not p.name.startswith(STAGING_PREFIX))
        if self._previous is not None and self._previous["kind"] != self.kind:
            raise OutputDirError(f"{self.option} {self.path}: holds a `fgslam {self._previous['kind']}` output; "
                                 f"choose another directory for this `fgslam {self.kind}` output")
        if self._previous is None and names and not self.force:
            foreign = [n for n in names if not _known(self.kind, n)]
            shown = ", ".join((foreign or names)[:5]) + (", ..." if len(foreign or names) > 5 else "")
            what = f"holds files fgslam did not write ({shown})" if foreign else \
                f"is not empty and has no fgslam manifest ({shown})"
            raise OutputDirError(f"{self.option} {self.path}: {what}; choose an empty or a new directory, "
                                 "or pass --force to write into it (files of other kinds are kept)")
        ours = [n for n in names if _known(self.kind, n)]
        if ours and not self.replace:
            shown = ", ".join(ours[:5])
            raise OutputDirError(f"{self.option} {self.path}: already holds {shown}; "
                                 f"{self.replace_hint or 'choose another directory'}")

    # -- writing --------------------------------------------------------------------------------
    def inside(self, path: Path) -> Path | None:
        """Where to write ``path`` if it lies in this directory (its staged twin), else None."""
        path = Path(path).expanduser().absolute()
        try:
            rel = path.relative_to(self.path)
        except ValueError:
            return None
        return self.staging / rel

    def write_manifest(self, status: str, names=None, **extra) -> Path:
        """Write OUT/manifest.json (atomically): ``status``, the command, and the files of the
        top-level entries ``names`` (default: those of this kind now in OUT)."""
        if names is None:
            names = [p.name for p in self.path.iterdir() if _known(self.kind, p.name)]
        data = {"kind": self.kind, "status": status, "fgslam_version": _version(),
                "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
                "started_utc": self._started, "written_utc": _utc_now(), **extra,
                "files": _listing(self.path, names) if status != WRITING else {}}
        text = json.dumps(data, indent=2, sort_keys=False)
        tmp = self.path / f".{MANIFEST}.tmp-{os.getpid()}"
        tmp.write_text(text)
        _fsync(tmp)
        os.replace(tmp, self.path / MANIFEST)
        return self.path / MANIFEST

    def commit(self) -> list[Path]:
        """Move the staged files into OUT (see module doc); returns their final paths."""
        if not self.staged:
            raise OutputDirError("commit() is for staged output directories")
        new = sorted(p.name for p in self.staging.iterdir())
        for p in self.staging.rglob("*"):
            if p.is_file():
                _fsync(p)
        if self._previous is not None:  # what the previous result wrote (or was writing), nothing else
            old_top = {rel.split("/")[0] for rel in self._previous.get("files", {})}
            old_top |= set(self._previous.get("replacing", []))
        else:  # written before manifests: its files by their names (others were refused)
            old_top = {p.name for p in self.path.iterdir() if _known(self.kind, p.name)}
        # an interrupted commit leaves this manifest: the next run knows every name involved
        self.write_manifest(WRITING, names=[], replacing=sorted(old_top | set(new)))
        trash = self.staging / ".replaced"
        trash.mkdir()
        for name in new:
            src, dst = self.staging / name, self.path / name
            if (src.is_dir() or dst.is_dir()) and dst.exists():
                os.rename(dst, trash / name)
            os.replace(src, dst)
        for name in sorted(old_top - set(new)):
            stale = self.path / name
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale)
            elif stale.exists() or stale.is_symlink():
                stale.unlink()
            log.info("removed %s, a file of the previous result that this one does not have", stale)
        self.write_manifest(COMPLETE, names=new)
        _fsync(self.path)
        shutil.rmtree(self.staging, ignore_errors=True)
        self._committed = True
        return [self.path / n for n in new]

    # -- leaving --------------------------------------------------------------------------------
    def _release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the lock
            self._fd = None

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self.staged and self.staging != self.path:
                shutil.rmtree(self.staging, ignore_errors=True)
            if self._created and not self._committed and self.staged:
                with contextlib.suppress(OSError):
                    self.path.rmdir()  # only when empty: a directory this run created and never filled
        finally:
            self._release()


def _version() -> str:
    from fgslam import __version__

    return __version__

"""``fgslam detect``'s output: the input bag with a rock topic added, written resumably.

Detection is the slow part (about a quarter of a second per pair on one core), so its results
are checkpointed: every :data:`CHUNK_FRAMES` frames go into ``chunk_NNNNNN.npz`` of a work
directory beside the output (``.<name>.detect/``, with ``source.json`` naming the input bag, its
size and the settings). A run that was stopped starts again after the last saved frame; a work
directory made from another bag or other settings is refused, naming it. When every pair is
done, the output bag is written in one go: every message of the input, unchanged (same topics,
types, definitions, QoS, log times), and one ``vision_msgs/Detection3DArray`` per pair on the
rock topic, in base_link, stamped and logged at the pair's stamp; then the work directory is
removed.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from fgslam.errors import BagError
from reloc.measurements import RockObservations

log = logging.getLogger(__name__)

CHUNK_FRAMES = 20


def _fingerprint(bag: Path, settings: dict) -> dict:
    files = sorted(p for p in (bag.iterdir() if bag.is_dir() else [bag]) if p.is_file())
    return {"bag": str(bag.resolve()), "bytes": sum(p.stat().st_size for p in files), "settings": settings}


class DetectCheckpoint:
    """The work directory of one detection (see module doc)."""

    def __init__(self, out: Path, bag: Path, settings: dict, restart: bool = False) -> None:
        self.dir = out.parent / f".{out.name}.detect"
        self.fingerprint = json.loads(json.dumps(_fingerprint(bag, settings), default=str))
        if restart and self.dir.exists():
            shutil.rmtree(self.dir)
        src = self.dir / "source.json"
        if self.dir.exists():
            saved = json.loads(src.read_text()) if src.is_file() else None
            if saved != self.fingerprint:
                raise BagError(f"{self.dir} holds a detection of another bag or with other settings "
                               f"({saved}); pass --restart to discard it")
        else:
            self.dir.mkdir(parents=True)
            tmp = src.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.fingerprint))
            tmp.replace(src)
        self.frames: list[tuple[int, RockObservations]] = self._load()
        self._buffer: list[tuple[int, RockObservations]] = []

    def _load(self) -> list[tuple[int, RockObservations]]:
        out = []
        for path in sorted(self.dir.glob("chunk_*.npz")):
            with np.load(path) as z:
                bounds = np.concatenate([[0], np.cumsum(z["n"])])
                for k, ns in enumerate(z["ns"]):
                    a, b = bounds[k], bounds[k + 1]
                    out.append((int(ns), RockObservations(float(ns) / 1e9, z["xyz"][a:b], z["cov"][a:b],
                                                          z["size"][a:b], z["score"][a:b])))
        if out:
            log.info("%s: resuming after %d saved frames", self.dir, len(out))
        return out

    @property
    def last_ns(self) -> int | None:
        return self.frames[-1][0] if self.frames else None

    def add(self, ns: int, obs: RockObservations) -> None:
        self.frames.append((ns, obs))
        self._buffer.append((ns, obs))
        if len(self._buffer) >= CHUNK_FRAMES:
            self.flush()

    def flush(self) -> None:
        """Save the frames not yet saved (atomically: a stopped run loses at most one chunk)."""
        if not self._buffer:
            return
        obs = [o for _, o in self._buffer]
        path = self.dir / f"chunk_{len(list(self.dir.glob('chunk_*.npz'))):06d}.npz"
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, ns=np.array([ns for ns, _ in self._buffer], dtype=np.int64), n=np.array([len(o) for o in obs]),
                 xyz=np.concatenate([o.xyz_base_m for o in obs]).reshape(-1, 3),
                 cov=np.concatenate([o.cov_base_m2 for o in obs]).reshape(-1, 3, 3),
                 size=np.concatenate([o.size_m for o in obs]), score=np.concatenate([o.score for o in obs]))
        tmp.replace(path)
        self._buffer = []

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def write_with_rocks(bag: Path, out: Path, rocks: Iterable[tuple[int, RockObservations]], rocks_topic: str,
                     frame_id_base: str = "base_link") -> dict[str, int]:
    """Write ``out``: every message of ``bag`` plus ``rocks`` ((ns, observations), stamp order) on
    ``rocks_topic``; returns the message count per topic. A partly written bag is removed."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    from fgslam.io.bag_reader import _open, _resolve
    from reloc.bag_spec import ROCKS_TYPE, ros2_msgtype
    from reloc.rock_bag import encode_rocks
    from sim.bag_writer import ROSBAG2_VERSION, message_builder

    builder = message_builder(frame_id_base)
    reader = _open(_resolve(bag), bag)
    counts: dict[str, int] = {}
    try:
        if rocks_topic in reader.topics:
            raise BagError(f"bag {bag} already has a topic {rocks_topic}; name another with --rocks-topic")
        writer = Writer(out, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            with writer:
                conns = {}
                for c in reader.connections:
                    if c.topic not in conns:
                        ext = c.ext
                        # the definition as recorded when it comes with its hash; otherwise (a bag
                        # without definitions, a bare storage file, ROS 1-style names) the
                        # project's typestore's, under the ROS 2 name
                        msgtype = c.msgtype if c.msgdef.data and c.digest else ros2_msgtype(c.msgtype)
                        source = ({"msgdef": c.msgdef.data, "rihs01": c.digest} if c.msgdef.data and c.digest
                                  else {"typestore": builder.ts})
                        if "typestore" in source and msgtype not in builder.ts.fielddefs:
                            raise BagError(f"bag {bag}: topic {c.topic}: type {c.msgtype} comes without its "
                                           "definition and type hash, and fgslam does not know it: the bag with "
                                           "rocks cannot be written")
                        conns[c.topic] = writer.add_connection(
                            c.topic, msgtype, **source,
                            serialization_format=getattr(ext, "serialization_format", "cdr"),
                            offered_qos_profiles=getattr(ext, "offered_qos_profiles", ()))
                rock_conn = writer.add_connection(rocks_topic, ROCKS_TYPE, typestore=builder.ts)
                pending: Iterator = iter(rocks)
                nxt = next(pending, None)

                def put_rocks(until_ns: float) -> None:
                    nonlocal nxt
                    while nxt is not None and nxt[0] <= until_ns:
                        msg = encode_rocks(nxt[1], nxt[0], builder)
                        writer.write(rock_conn, nxt[0], builder.ts.serialize_cdr(msg, ROCKS_TYPE))
                        counts[rocks_topic] = counts.get(rocks_topic, 0) + 1
                        nxt = next(pending, None)

                for conn, ts, raw in reader.messages():
                    put_rocks(ts)
                    writer.write(conns[conn.topic], ts, raw)
                    counts[conn.topic] = counts.get(conn.topic, 0) + 1
                put_rocks(float("inf"))
        except BaseException:
            shutil.rmtree(out, ignore_errors=True)
            raise
    finally:
        reader.close()
    return counts

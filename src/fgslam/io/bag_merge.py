"""One pass over a bag for :class:`fgslam.io.bag_reader.BagSource`: raw messages in blocks ->
measurements (the motion messages vectorised, :mod:`fgslam.io.cdr_batch`) -> the per-topic stamp
repairs -> one stream in :func:`reloc.measurements.sort_key` order, released once no message
still to come can precede it (``reorder_window_s`` behind the newest stamp)."""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path

from fgslam.errors import BagError
from fgslam.io.bag_decode import has_nonfinite, header_ns, same_measurement
from fgslam.io.bag_report import TopicReport
from fgslam.io.cdr_batch import LAYOUTS, decode_block, row_finite
from reloc.bag_spec import CdrParser, MessageContentError, UnknownFrameError
from reloc.errors import MeasurementError
from reloc.measurements import Measurement, sort_key

BLOCK = 2048  # messages decoded at once (the vectorised decoders' batch)


def usable_parser(role, msgtype: str, reader) -> CdrParser | None:
    """The role's own parser of raw messages (a landmark kind's fast path) where the topic's type
    is the parser's and the bag defines it as fgslam does; else None (rosbags deserializes)."""
    p = role.parser
    return p if p is not None and msgtype == p.msgtype and p.accepts(reader.typestore) else None


class BagPass:
    """One pass over a bag: blocks of raw messages -> measurements -> per-topic stamp repairs ->
    one stream in sort_key order, released once no message still to come can precede it."""

    def __init__(self, roles, topics, reader, path: Path, repair: bool, window_s: float) -> None:
        self.role = {r.topic: r for r in roles if r.topic in topics}
        self.reader, self.path, self.repair = reader, path, repair
        self.window_ns = round(window_s * 1e9)
        self.counts = {t: {"msgtype": reader.topics[t].msgtype, "n_messages": 0, "n_kept": 0, "n_reordered": 0,
                           "n_duplicates": 0, "n_conflicts": 0, "n_nonfinite": 0, "n_invalid": 0, "n_late": 0,
                           "n_log_stamped": 0, "first_problem": ""} for t in self.role}
        self.raw: dict[str, list] = {t: [] for t in self.role}  # (arrival, log_ns, raw) waiting for decoding
        self.parser = {t: p for t, r in self.role.items() if (p := usable_parser(r, self.counts[t]["msgtype"], reader))}
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
        parser = self.parser.get(topic)
        for k, (arrival, log_ns, raw) in enumerate(items):
            try:
                msg = parser.parse(raw) if parser is not None else None
                parsed = msg is not None
                if not parsed:
                    msg = self.reader.deserialize(raw, msgtype)
            except Exception as exc:
                raise BagError(f"bag {self.path}: topic {topic}: message {n0 + k} cannot be deserialized "
                               f"(corrupt bag): {type(exc).__name__}: {exc}") from exc
            if parsed:  # the parser's output carries its header's stamp (CdrParser)
                ns = msg.stamp_ns
            elif hasattr(msg, "header"):
                ns = header_ns(msg.header)
            else:
                ns = int(log_ns)
                counts["n_log_stamped"] += 1
            try:
                m = role.decode(msg, ns)
            except UnknownFrameError as exc:
                raise BagError(f"bag {self.path}: topic {topic}: {exc}") from None
            except (MeasurementError, MessageContentError) as exc:
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
            _, ns, _, topic, m = heapq.heappop(heap)
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



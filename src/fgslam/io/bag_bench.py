"""Bag size and write/read throughput on a synthetic stream at the simulator's rates.

Values of the synthetic stream are random (white), so they compress worse than a smooth
simulated traverse: the size figure is an upper bound for simulator bags of the same rates.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.io.bag_reader import read_bag
from fgslam.io.synthetic import SyntheticStreamConfig, synthetic_stream
from reloc.measurements import RockObservations

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BagBenchResult:
    """Sizes in bytes, times in seconds, throughput in messages per second."""

    duration_s: float
    n_messages: int
    n_rocks: int
    n_bytes: int
    write_s: float
    read_s: float

    @property
    def bytes_per_100s(self) -> float:
        return self.n_bytes * 100.0 / self.duration_s

    @property
    def write_msgs_per_s(self) -> float:
        return self.n_messages / self.write_s

    @property
    def read_msgs_per_s(self) -> float:
        return self.n_messages / self.read_s


def bench_bag(
    config: SyntheticStreamConfig | None = None, seed: int = 0, out_dir: Path | None = None
) -> BagBenchResult:
    """Write and read back one synthetic bag (default: 100 s, 30 Hz motion topics, 2 Hz rocks)."""
    from sim.bag_writer import write_bag

    config = config or SyntheticStreamConfig(duration_s=100.0, empty_frame_every=0)
    stream = synthetic_stream(config, np.random.default_rng(seed))
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        path = Path(tmp) / "bench_bag"
        t0 = time.perf_counter()
        summary = write_bag(path, stream)
        t1 = time.perf_counter()
        got = read_bag(path)
        t2 = time.perf_counter()
    if len(got.measurements) != len(stream):  # pragma: no cover - guarded by the round-trip tests
        raise RuntimeError(f"bench bag read back {len(got.measurements)} of {len(stream)} messages")
    result = BagBenchResult(
        duration_s=config.duration_s,
        n_messages=summary.n_messages,
        n_rocks=sum(len(m) for m in stream if isinstance(m, RockObservations)),
        n_bytes=summary.n_bytes,
        write_s=t1 - t0,
        read_s=t2 - t1,
    )
    log.info("bag bench: %s", result)
    return result

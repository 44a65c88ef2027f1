"""A short simulated yard written as a ``fgslam sim`` directory, for the benchmarks' tests."""

from __future__ import annotations

import dataclasses
from pathlib import Path


def write_yard_dir(out: Path, world: str, seed: int, distance_m: float, faults=None) -> Path:
    """Simulate ``distance_m`` of ``world`` with ``seed`` (and ``faults``, a
    :class:`sim.faults.FaultsConfig`) and write it to ``out``; returns ``out``."""
    from fgslam.io.sim_dir import write_sim_dir
    from sim.config import SimConfig, TraverseConfig
    from sim.simulate import simulate

    cfg = SimConfig(world=world, seed=seed)
    cfg = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse or TraverseConfig(), distance_m=distance_m))
    if faults is not None:
        cfg = dataclasses.replace(cfg, faults=faults)
    write_sim_dir(simulate(cfg), out)
    return out

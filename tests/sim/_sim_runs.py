"""Seeded simulator runs shared by the sim tests (built once per session: they are the expensive part)."""

from __future__ import annotations

from functools import cache

from sim.config import SimConfig, TraverseConfig
from sim.simulate import simulate


@cache
def short_run():
    """A seeded 30 m traverse in my2022 with every default sensor."""
    return simulate(SimConfig(world="my2022", seed=3, traverse=TraverseConfig(distance_m=30.0)))


@cache
def dense_run():
    """A seeded 15 m traverse in the rock-dense my2020 (heavy occlusion)."""
    return simulate(SimConfig(world="my2020", seed=5, traverse=TraverseConfig(distance_m=15.0)))

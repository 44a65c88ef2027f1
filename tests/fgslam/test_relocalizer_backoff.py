"""The relocalizer's attempt backoff: consecutive misses stretch the period, a fix resets it."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.relocalizer import Relocalizer, RelocalizerConfig, RelocalizerError
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.measurements import RockCatalog


def _map(xy: np.ndarray, sizes: np.ndarray) -> LandmarkMap:
    n = len(xy)
    return LandmarkMap(np.arange(n), np.column_stack([xy, np.zeros(n)]), np.tile(np.eye(3) * 1e-4, (n, 1, 1)),
                       sizes, np.full(n, 5), "rocks")


def test_misses_double_the_period_up_to_the_cap_and_a_fix_resets_it():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-15, 15, (40, 2))
    sizes = rng.uniform(0.3, 1.5, 40)
    cat = RockCatalog(xy, sizes, np.ones(40))
    reloc = Relocalizer(cat, {"min_new_observations": 0, "backoff_after": 3, "backoff_max_period_s": 10.0,
                              "min_travel_m": 0.0, "min_turn_deg": 0.0})
    est = PoseEstimate(t=0.0, T_world_base=np.eye(4), cov=np.eye(6) * 1e-4)
    elsewhere = _map(rng.uniform(-15, 15, (40, 2)), sizes)  # a map of no place in the catalog
    periods, statuses = [reloc.period_s], []
    for _ in range(6):
        statuses.append(reloc.attempt(elsewhere, est).status)
        periods.append(reloc.period_s)
    assert statuses == ["no match"] * 6
    assert periods == [2.0, 2.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert reloc.attempt(_map(xy, sizes), est).status == "fix"  # the map where it is
    assert reloc.period_s == 2.0
    off = Relocalizer(cat, {"min_new_observations": 0, "backoff_after": 0})
    for _ in range(12):
        off.attempt(elsewhere, est)
    assert off.period_s == 2.0


def test_too_few_landmarks_is_not_a_miss():
    cat = RockCatalog(np.random.default_rng(0).uniform(0, 10, (20, 2)), np.full(20, 0.5), np.ones(20))
    reloc = Relocalizer(cat, {"min_new_observations": 0, "backoff_after": 1})
    est = PoseEstimate(t=0.0, T_world_base=np.eye(4), cov=np.eye(6) * 1e-4)
    tiny = _map(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.full(3, 0.5))
    for _ in range(5):
        assert reloc.attempt(tiny, est).status == "too few landmarks"
    assert reloc.period_s == 2.0


def test_backoff_settings_are_checked():
    with pytest.raises(RelocalizerError, match="backoff_max_period_s"):
        RelocalizerConfig(backoff_max_period_s=0.0)
    with pytest.raises(RelocalizerError, match="backoff_after"):
        RelocalizerConfig(backoff_after=-1)


def test_wrapped_relocalizers_follow_the_inner_backoff():
    """A wrapper (heights, wrong fixes, the crater bench's counter) reports the period the inner
    relocalizer has now, not the one it had when wrapped, and forwards its other attributes."""
    from fgslam.bench.craters import CraterBenchConfig, _CountingRelocalizer
    from fgslam.fix_sources import WrappedProducer

    rng = np.random.default_rng(4)
    sizes = rng.uniform(0.3, 1.5, 40)
    cat = RockCatalog(rng.uniform(-15, 15, (40, 2)), sizes, np.ones(40))
    reloc = Relocalizer(cat, {"min_new_observations": 0, "backoff_after": 1, "min_travel_m": 0.0, "min_turn_deg": 0.0,
                              "single_landmark": False})  # one rock of a random map may sit in a catalog rock's gate
    wrapped = [WrappedProducer(reloc), _CountingRelocalizer(reloc, cat, None, CraterBenchConfig())]
    est = PoseEstimate(t=0.0, T_world_base=np.eye(4), cov=np.eye(6) * 1e-4)
    elsewhere = _map(rng.uniform(-15, 15, (40, 2)), sizes)
    for _ in range(3):
        assert reloc.attempt(elsewhere, est).status == "no match"
    assert reloc.period_s == 16.0
    for w in wrapped:
        assert w.period_s == 16.0 and w.kinds == ("rocks",) and w.config is reloc.config
        assert w.n_crops_built == reloc.n_crops_built  # forwarded as it is
        with pytest.raises(AttributeError):
            w.no_such_attribute

"""Matching at crater scale: landmarks tens of metres apart, half of the local map uncatalogued,
a prior's guess verified on its own (tracking) and held to the same false-alarm bound."""

from __future__ import annotations

import numpy as np
import pytest

from reloc import Catalog, ConstellationMatcher, MatcherConfig
from reloc.matcher import MatchPrior
from reloc.procrustes import Similarity2D

DENSITY = 0.002  # per m^2: a crater field of >= 1 m craters, ~20 m apart


def _field(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / DENSITY)
    return rng.uniform(0, side, (n, 2)), 1.0 + 1.5 * rng.pareto(2.0, n)


@pytest.fixture(scope="module")
def field():
    xy, size = _field(4000, 3)
    return xy, size, Catalog(xy, size)


def _config(**kw) -> MatcherConfig:
    """The crater relocalizer's matcher settings, with ``kw`` over them."""
    from fgslam.crater_relocalizer import CRATER_MATCHER
    from reloc.config import config_from_dict

    return config_from_dict(MatcherConfig, {**CRATER_MATCHER, **kw}, where="matcher.")


def _query(xy, size, rng, n_cat=6, n_extra=6, sigma=0.15):
    """The n_cat catalogued landmarks nearest a random point (jittered, sizes off by ~8 %) and
    n_extra uncatalogued ones among them, in world coordinates: (local_xy, local_size)."""
    c = rng.uniform(100.0, np.ptp(xy[:, 0]) - 100.0, 2)
    idx = np.argsort(np.hypot(*(xy - c).T))[:n_cat]
    r = np.hypot(*(xy[idx] - c).T).max()
    ang, rr = rng.uniform(0, 2 * np.pi, n_extra), r * np.sqrt(rng.random(n_extra))
    world = np.vstack([xy[idx] + rng.normal(0, sigma, (n_cat, 2)), c + np.c_[rr * np.cos(ang), rr * np.sin(ang)]])
    sizes = np.r_[size[idx] * np.exp(rng.normal(0, 0.08, n_cat)), 1.0 + rng.pareto(2.0, n_extra)]
    return world, sizes


def _about_centroid(xy: np.ndarray, theta: float, shift: np.ndarray) -> Similarity2D:
    c = xy.mean(axis=0)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return Similarity2D(theta, c - rot @ c + shift, 1.0)


def test_heading_bins_follow_the_landmark_spacing(field):
    """Six catalogued craters among twelve: with vote bins sized for rocks 1.5 m apart, every
    verified bin is charged for ~1000s of poses and no match convinces; with the bins sized from
    the local triangles' sides (heading_arm_m None), every one is found, at the true pose."""
    xy, size, cat = field
    rocks, craters = ConstellationMatcher(cat, _config(heading_arm_m=1.5)), ConstellationMatcher(cat, _config())
    rng = np.random.default_rng(1)
    found_with_rock_bins = 0
    for _ in range(8):
        local, sizes = _query(xy, size, rng)
        prior = MatchPrior(local.mean(axis=0), 5.0)
        found_with_rock_bins += rocks.match(local, sizes, prior) is not None
        res = craters.match(local, sizes, prior)
        assert res is not None and res.n_inliers >= 5 and res.log10_false_alarm <= -3.0
        # the catalogued six land on their own entries: the pose is the identity
        c = local.mean(axis=0)
        assert np.hypot(*(res.apply(c[None])[0] - c)) < 0.3 and abs(res.rotation_rad) < np.radians(0.5)
    assert found_with_rock_bins <= 2


def test_a_guess_is_verified_alone_and_refuses_maps_that_are_not_there(field):
    """A localized rover's guess (0.14 m and 0.1 deg off) is verified without a search; guesses
    that put a map where it is not (moved 50-100 m, over the catalog) are refused, at a bound
    100x more lenient than the default too."""
    xy, size, cat = field
    matcher = ConstellationMatcher(cat, _config())
    rng = np.random.default_rng(4)
    for _ in range(6):
        local, sizes = _query(xy, size, rng)
        guess = _about_centroid(local, np.radians(0.1), np.array([0.1, -0.1]))
        res = matcher.match(local, sizes, MatchPrior(local.mean(axis=0), 5.0, guess))
        assert res is not None and res.from_guess and res.n_hypotheses == 1
        c = local.mean(axis=0)
        assert np.hypot(*(res.apply(c[None])[0] - c)) < 0.3
    lenient = ConstellationMatcher(cat, _config(max_log10_false_alarm=-1.0, early_exit_log10=-1.0))
    false = 0
    for _ in range(60):
        local, sizes = _query(xy, size, rng, n_cat=12, n_extra=0)
        local = local + rng.uniform(50.0, 100.0, 2) * rng.choice([-1.0, 1.0], 2)
        identity = Similarity2D(0.0, np.zeros(2), 1.0)
        false += lenient.match(local, sizes, MatchPrior(local.mean(axis=0), 5.0, identity)) is not None
    assert false <= 6  # the bound: 10 % per attempt

"""Craters: size-frequency model and sampling, equilibrium cap, morphology, ejecta blocks."""

from __future__ import annotations

import numpy as np
import pytest

from sim.craters import (
    INFLUENCE_RADIUS,
    Craters,
    CraterSFD,
    EjectaConfig,
    crater_relief,
    depth_ratio,
    ejecta_blocks,
    expected_blocks,
    hartmann_age_scale,
    rim_ratio,
    sample_craters,
    stamp_craters,
)
from sim.errors import SimError
from sim.terrain import Heightmap


def test_hartmann_table_and_age_scale():
    assert hartmann_age_scale(1.0) == pytest.approx(1.0)
    # f(T) is linear in T for young surfaces, exponential before 3 Gyr
    assert hartmann_age_scale(0.1) == pytest.approx(0.1, rel=0.01)
    assert hartmann_age_scale(3.5) > 5.0
    sfd = CraterSFD(age_gyr=1.0, equilibrium=False, d_min_m=1.0, d_max_m=2000.0)
    # Hartmann (2005) 1 Gyr isochron, bin [1, 1.41) km: 3.08e-4 per km^2; [15.65, 22.1) m: 191 per km^2
    assert sfd.bin_density_per_m2(np.array([1000.0]))[0] * 1e6 == pytest.approx(3.08e-4, rel=1e-6)
    assert sfd.bin_density_per_m2(np.array([1000.0 * 2**-6]))[0] * 1e6 == pytest.approx(191.0, rel=1e-6)


def test_equilibrium_caps_small_craters_of_old_surfaces():
    old = CraterSFD(age_gyr=3.0)
    d = np.array([2.0, 8.0, 150.0])
    eq_cum = 10**-1.14 * (d / 1000.0) ** -1.83 * 1e-6
    eq_bin = eq_cum * (1 - 2 ** (-1.83 / 2))
    dens = old.bin_density_per_m2(d)
    assert old.saturation_ratio(d)[:2].min() > 1.0  # saturated there ...
    assert dens[:2] == pytest.approx(eq_bin[:2], rel=1e-6)  # ... and capped at equilibrium
    assert old.saturation_ratio(d)[2] < 1.0 and dens[2] < eq_bin[2]  # production where unsaturated
    young = CraterSFD(age_gyr=0.01)
    assert np.all(young.bin_density_per_m2(d) < dens)


def test_sampled_population_follows_the_model():
    sfd = CraterSFD(age_gyr=0.5, d_min_m=1.0, d_max_m=200.0)
    extent = (0.0, 2000.0, 0.0, 1000.0)
    c = sample_craters(sfd, extent, np.random.default_rng(4))
    area = 2000.0 * 1000.0
    for lo, hi in ((1.0, 2.0), (2.0, 8.0), (8.0, 32.0), (32.0, 200.0)):
        n = np.sum((c.diameter_m >= lo) & (c.diameter_m < hi))
        lam = sfd.expected_count(area, lo, hi)
        assert abs(n - lam) < 4.0 * np.sqrt(lam) + 1, (lo, hi, n, lam)
    assert c.diameter_m.min() >= 1.0 and c.diameter_m.max() < 200.0
    assert np.all((c.xy_m[:, 0] >= 0) & (c.xy_m[:, 0] <= 2000) & (c.xy_m[:, 1] >= 0) & (c.xy_m[:, 1] <= 1000))
    # unsaturated large craters are less degraded than saturated small ones
    assert c.degradation[c.diameter_m > 50].mean() < c.degradation[c.diameter_m < 3].mean()
    again = sample_craters(sfd, extent, np.random.default_rng(4))
    assert np.array_equal(c.xy_m, again.xy_m) and np.array_equal(c.degradation, again.degradation)


def _flat(size_m=120.0, res_m=0.1):
    n = round(size_m / res_m) + 1
    return Heightmap(np.zeros((n, n)), (-size_m / 2, size_m / 2, -size_m / 2, size_m / 2))


def test_fresh_crater_depth_rim_and_ejecta():
    hm = _flat()
    c = Craters([[0.0, 0.0]], [20.0], [0.0], [7])
    z = stamp_craters(hm, c)
    res = hm.spacing_m[0]
    xs = np.linspace(-60, 60, z.z_m.shape[1])
    row = z.z_m[z.z_m.shape[0] // 2]
    rim = row.max()
    assert rim == pytest.approx(0.04 * 20.0, abs=0.01)
    assert rim - row.min() == pytest.approx(0.2 * 20.0, abs=0.01)  # depth / D = 0.2
    assert c.depth_m[0] == pytest.approx(4.0) and c.rim_height_m[0] == pytest.approx(0.8)
    assert abs(xs[np.argmax(row)]) == pytest.approx(10.0, abs=2 * res)  # rim crest at R
    assert row[np.argmin(row)] == row[len(row) // 2]  # deepest at the centre
    far = np.abs(xs) > INFLUENCE_RADIUS * 10.0
    assert np.all(row[far] == 0.0)
    # ejecta blanket: raised outside the rim, thinning outwards
    out = (xs > 11.0) & (xs < 29.0)
    assert np.all(row[out] > 0) and np.all(np.diff(row[out]) < 0)
    # the point query agrees with the grid
    assert crater_relief(np.array([[3.0, 4.0]]), c.xy_m, c.diameter_m, c.degradation)[0] == pytest.approx(
        z.height_at(np.array([[3.0, 4.0]]))[0], abs=0.01)


def test_degraded_craters_are_shallower_with_softer_rims():
    g = np.linspace(0.0, 1.0, 9)
    d, r = depth_ratio(g), rim_ratio(g)
    assert np.all(np.diff(d) < 0) and np.all(np.diff(r) < 0)
    assert d[-1] < 0.4 * d[0] and r[-1] < 0.5 * r[0]
    hm = _flat()
    fresh = stamp_craters(hm, Craters([[0.0, 0.0]], [20.0], [0.0], [1])).z_m
    old = stamp_craters(hm, Craters([[0.0, 0.0]], [20.0], [0.8], [1])).z_m
    # softened rim: the steepest slope of the degraded crater is much gentler
    gf = np.abs(np.gradient(fresh[fresh.shape[0] // 2], 0.1)).max()
    go = np.abs(np.gradient(old[old.shape[0] // 2], 0.1)).max()
    assert go < 0.6 * gf


def test_overlapping_craters_superpose():
    hm = _flat()
    a = Craters([[0.0, 0.0]], [30.0], [0.2], [1])
    b = Craters([[12.0, 0.0]], [8.0], [0.0], [2])
    both = stamp_craters(hm, Craters.concat([a, b])).z_m
    assert np.allclose(both, stamp_craters(hm, a).z_m + stamp_craters(hm, b).z_m)


def test_crater_table_rejects_bad_input():
    with pytest.raises(SimError, match="diameter_m must be positive"):
        Craters([[0.0, 0.0]], [-1.0], [0.0], [1])
    with pytest.raises(SimError, match="disagree"):
        Craters([[0.0, 0.0]], [1.0, 2.0], [0.0], [1])
    with pytest.raises(SimError, match="NaN"):
        Craters([[np.nan, 0.0]], [1.0], [0.0], [1])
    with pytest.raises(SimError, match="age_gyr"):
        CraterSFD(age_gyr=0.0)


def test_ejecta_blocks_around_fresh_craters_only_and_seeded_per_crater():
    cfg = EjectaConfig()
    c = Craters([[0.0, 0.0], [500.0, 0.0], [0.0, 500.0]], [60.0, 60.0, 6.0], [0.0, 0.9, 0.0], [11, 12, 13])
    blocks = ejecta_blocks(c, seed=3, cfg=cfg)
    assert set(np.unique(blocks.crater_id)) == {11}  # degraded and small craters have none
    lam = expected_blocks(np.array([60.0]), np.array([0.0]), cfg)[0]
    assert abs(len(blocks) - lam) < 4 * np.sqrt(lam)
    r = np.linalg.norm(blocks.xy_m, axis=1) / 30.0
    assert r.min() >= cfg.inner_radius - 1e-9 and r.max() <= cfg.outer_radius + 1e-9
    assert np.mean(r < 1.5) > 0.5  # concentrated near the rim
    l_max = 0.29 * 60.0**0.7
    assert blocks.diameter_m.min() >= 0.1 and blocks.diameter_m.max() <= min(l_max, 3.0)
    alone = ejecta_blocks(c.subset([0]), seed=3, cfg=cfg)
    assert np.array_equal(alone.xy_m, blocks.xy_m)  # the same blocks whoever asks

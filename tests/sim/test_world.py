"""World presets: size, relief, rock count and size distribution; rocks resting on the terrain."""

from __future__ import annotations

import numpy as np
import pytest

from sim.config import WorldGenConfig
from sim.errors import SimError
from sim.rocks import sample_diameters
from sim.terrain import Heightmap, fractal_heightmap
from sim.world import PRESETS, build_world


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_preset_dimensions_relief_and_rock_count(name):
    p = PRESETS[name]
    w = build_world(name, seed=1, cfg=WorldGenConfig(resolution_m=0.5, n_rocks=60))
    xmin, xmax, ymin, ymax = w.extent
    assert xmax - xmin == pytest.approx(p.size_x_m) and ymax - ymin == pytest.approx(p.size_y_m)
    assert np.ptp(w.terrain.z_m) == pytest.approx(p.relief_m, rel=1e-9)
    assert len(w.rocks) == 60
    assert np.all(w.terrain.contains(w.rocks.xyz_m[:, :2]))


def test_default_rock_count_and_power_law_sizes():
    w = build_world("my2021", seed=0, cfg=WorldGenConfig(resolution_m=0.5))
    size = w.rocks.size_m
    assert len(size) == PRESETS["my2021"].n_rocks
    assert 0.07 < size.min() and size.max() < 1.9
    # many small, few large: cumulative counts fall off like a power law
    n_small, n_mid, n_big = (np.sum(size > d) for d in (0.15, 0.3, 0.6))
    assert n_small > 2 * n_mid > 4 * n_big > 0


def test_sampled_diameters_follow_the_cumulative_power_law():
    d = sample_diameters(200_000, 0.1, 1.5, 2.0, np.random.default_rng(0))
    frac = np.mean(d > 0.2)
    expected = (0.2**-2 - 1.5**-2) / (0.1**-2 - 1.5**-2)
    assert frac == pytest.approx(expected, abs=0.005)


def test_rocks_rest_on_the_terrain():
    w = build_world("cnes", seed=2, cfg=WorldGenConfig(resolution_m=0.3, n_rocks=200))
    r = w.rocks
    for k in range(len(r)):
        v = r.vertices_m[np.unique(r.triangles[r.triangle_rock == k])]
        ground = w.height_at(v[:, :2])
        below = ground - v[:, 2]
        assert below.max() > 0.0  # its base is in the ground (embedded) ...
        assert below.max() < 0.5 * r.height_m[k] + 0.05  # ... but only partly
        assert v[:, 2].max() > w.height_at(r.xyz_m[k:k + 1, :2])[0]  # and it sticks out


def test_world_is_seeded():
    a = build_world("my2022", seed=5, cfg=WorldGenConfig(resolution_m=0.5))
    b = build_world("my2022", seed=5, cfg=WorldGenConfig(resolution_m=0.5))
    c = build_world("my2022", seed=6, cfg=WorldGenConfig(resolution_m=0.5))
    assert np.array_equal(a.terrain.z_m, b.terrain.z_m) and np.array_equal(a.rocks.xyz_m, b.rocks.xyz_m)
    assert not np.array_equal(a.terrain.z_m, c.terrain.z_m)


def test_heightmap_bilinear_height_gradient_and_normal():
    rng = np.random.default_rng(0)
    hm = fractal_heightmap((-5, 5, -4, 4), 2.0, 0.1, rng)
    xy = rng.uniform([-4.9, -3.9], [4.9, 3.9], (50, 2))
    eps = 1e-5
    gx = (hm.height_at(xy + [eps, 0]) - hm.height_at(xy - [eps, 0])) / (2 * eps)
    gy = (hm.height_at(xy + [0, eps]) - hm.height_at(xy - [0, eps])) / (2 * eps)
    np.testing.assert_allclose(hm.gradient_at(xy), np.column_stack([gx, gy]), atol=1e-4)
    n = hm.normal_at(xy)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    np.testing.assert_allclose(n[:, :2] / n[:, 2:], -np.column_stack([gx, gy]), atol=1e-4)
    # a plane is reproduced exactly
    gxg, gyg = np.meshgrid(np.linspace(0, 2, 5), np.linspace(0, 1, 3))
    plane = Heightmap(0.3 * gxg - 0.2 * gyg + 1.0, (0, 2, 0, 1))
    q = np.array([[0.3, 0.7], [1.9, 0.1]])
    np.testing.assert_allclose(plane.height_at(q), 0.3 * q[:, 0] - 0.2 * q[:, 1] + 1.0)
    verts, tris = plane.mesh()
    assert verts.shape == (15, 3) and tris.shape == (16, 3)


def test_unknown_world_and_bad_heightmap_raise():
    with pytest.raises(SimError, match="unknown world"):
        build_world("olympus_mons", seed=0)
    with pytest.raises(SimError, match="NaN"):
        Heightmap(np.array([[0.0, np.nan], [0.0, 0.0]]), (0, 1, 0, 1))
    with pytest.raises(SimError, match="extent"):
        Heightmap(np.zeros((2, 2)), (1, 0, 0, 1))

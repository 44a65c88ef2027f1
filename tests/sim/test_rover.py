"""Route planner, pure-pursuit rover and terrain following; preset traverse length and duration."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from sim.config import RoverConfig, SimConfig, TraverseConfig, WorldGenConfig
from sim.rover import PlanarPath, drive_route, terrain_poses
from sim.simulate import _drive, resolve_config
from sim.terrain import Heightmap
from sim.world import PRESETS, build_world


@pytest.mark.parametrize("name", ["cnes", "my2020"])
def test_preset_traverse_length_and_duration_within_5_percent(name):
    """The whole reference traverse, planner and controller only (no sensors)."""
    cfg = SimConfig(world=name, seed=4, worldgen=WorldGenConfig(resolution_m=0.3))
    world = build_world(name, cfg.seed, cfg.worldgen)
    cfg = resolve_config(cfg, world)
    _, path, _ = _drive(world, cfg, np.random.default_rng(0))
    T = terrain_poses(world.terrain, path, cfg.rover)
    p = T[:, :3, 3]
    distance = np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))
    duration = (len(p) - 1) * path.dt_s
    assert distance == pytest.approx(PRESETS[name].traverse_m, rel=0.05)
    assert duration == pytest.approx(PRESETS[name].duration_s, rel=0.05)
    # the rover stays inside the world, away from its edges, and never jumps
    assert np.all(world.terrain.contains(p[:, :2], margin_m=cfg.traverse.edge_margin_m - 1.5))
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step.max() < cfg.rover.max_speed_mps * path.dt_s * 1.5
    # it keeps clear of big rocks
    big = world.rocks.size_m >= 0.8
    d = np.linalg.norm(p[::10, None, :2] - world.rocks.xyz_m[None, big, :2], axis=2) - world.rocks.size_m[big] / 2
    assert d.min() > 0.0


def test_pure_pursuit_follows_a_square_route_and_turns_in_place():
    flat = Heightmap(np.zeros((21, 21)), (-10, 10, -10, 10))
    wp = np.array([[0, 0], [6, 0], [6, 6], [0, 6], [0, 0.0]])
    path = drive_route(flat, wp, 20.0, 0.15, RoverConfig(), 1 / 30)
    xy = np.column_stack([path.x_m, path.y_m])
    # distance to the route polyline stays small
    seg_d = []
    for a, b in itertools.pairwise(wp):
        ab = b - a
        u = np.clip((xy - a) @ ab / (ab @ ab), 0, 1)
        seg_d.append(np.linalg.norm(a + u[:, None] * ab - xy, axis=1))
    assert np.min(seg_d, axis=0).max() < 0.6
    assert np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)) == pytest.approx(20.0, abs=0.05)
    assert len(path.stop_ticks) == 0  # 90-degree corners are driven round
    # a hairpin makes the rover stop and turn in place
    hairpin = drive_route(flat, np.array([[0, 0], [6, 0], [0.5, 1.0]]), 10.0, 0.15, RoverConfig(), 1 / 30)
    assert len(hairpin.stop_ticks) == 1
    k = hairpin.stop_ticks[0]
    assert hairpin.x_m[k] == pytest.approx(6.0, abs=1.3)
    still = slice(k, k + 60)
    assert np.ptp(hairpin.x_m[still]) < 1e-9 and np.ptp(hairpin.y_m[still]) < 1e-9
    assert np.ptp(hairpin.yaw_rad[still]) > 0.3  # turning on the spot


def test_terrain_poses_follow_a_tilted_plane():
    gx, gy = np.meshgrid(np.linspace(-10, 10, 41), np.linspace(-10, 10, 41))
    slope = Heightmap(0.2 * gx + 0.1 * gy, (-10, 10, -10, 10))
    yaw = np.linspace(0, 2 * np.pi, 9)
    path = PlanarPath(1 / 30, np.zeros(9), np.ones(9), yaw, np.zeros(0, dtype=int))
    cfg = RoverConfig()
    T = terrain_poses(slope, path, cfg)
    n = slope.normal_at(np.array([[0.0, 1.0]]))[0]
    for Tk, yk in zip(T, yaw):
        R = Tk[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R[:, 2], n, atol=1e-9)  # body z = terrain normal
        heading = R[:2, 0] / np.linalg.norm(R[:2, 0])
        np.testing.assert_allclose(heading, [np.cos(yk), np.sin(yk)], atol=1e-9)
        ground = 0.2 * 0 + 0.1 * 1.0
        np.testing.assert_allclose(Tk[:3, 3], [0, 1, ground] + cfg.base_height_m * n, atol=1e-9)


def test_any_traverse_length_and_duration():
    cfg = SimConfig(world="my2022", seed=1, worldgen=WorldGenConfig(resolution_m=0.3, n_rocks=50),
                    traverse=TraverseConfig(distance_m=15.0, duration_s=200.0))
    world = build_world(cfg.world, cfg.seed, cfg.worldgen)
    cfg = resolve_config(cfg, world)
    _, path, _ = _drive(world, cfg, np.random.default_rng(1))
    T = terrain_poses(world.terrain, path, cfg.rover)
    assert np.sum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)) == pytest.approx(15.0, rel=0.03)
    assert (len(T) - 1) * path.dt_s == pytest.approx(200.0, rel=0.01)
    # a duration too short for the speed limit is stretched to what the rover can do
    fast = dataclasses.replace(cfg, traverse=dataclasses.replace(cfg.traverse, duration_s=20.0))
    _, path, v = _drive(world, fast, np.random.default_rng(1))
    assert v == pytest.approx(cfg.rover.max_speed_mps)
    assert (len(path.x_m) - 1) * path.dt_s > 15.0 / cfg.rover.max_speed_mps

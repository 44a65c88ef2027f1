"""Routes over tiled worlds: the rover never comes back, avoids what it must, stops when asked,
and the revisit count itself is right."""

from __future__ import annotations

import numpy as np
import pytest

from sim.craters import depth_ratio
from sim.tiled.drive import Driver
from sim.tiled.presets import preset_config, resolve_tiled_config
from sim.tiled.route import revisits
from sim.tiled.world import TiledWorld

SHORT_LEGS = {"strategic_min_m": 40.0, "strategic_max_m": 70.0, "path_clearance_m": 30.0, "heading_sigma_deg": 60.0,
              "edge_margin_m": 20.0, "stop_s": 20.0}


def _drive(name: str, distance_m: float, seed: int, **route):
    cfg = resolve_tiled_config(preset_config(name, seed, {"traverse": {"distance_m": distance_m},
                                                         "tiled": {"size_m": 600.0, "route": {**SHORT_LEGS, **route}}}))
    world = TiledWorld(name, seed, cfg.tiled)
    driver = Driver(world, cfg, np.random.default_rng([seed, 200]))
    segs = list(driver.segments())
    xy = np.concatenate([np.column_stack([s.path.x_m, s.path.y_m]) for s in segs])
    t = np.arange(len(xy)) / cfg.sensors.imu.rate_hz
    return cfg, world, driver, segs, t, xy


def test_revisit_count():
    t = np.arange(200.0) * 10.0  # 10 s per metre
    line = np.column_stack([np.arange(200.0), np.zeros(200)])
    assert revisits(t, line) == 0
    out_and_back = np.vstack([line[:100], line[99::-1] + [0.0, 5.0]])  # back along a line 5 m off
    assert revisits(t, out_and_back) > 50
    still = np.zeros((200, 2))  # standing still is not coming back
    assert revisits(t, still) == 0


@pytest.mark.slow
def test_long_drive_never_comes_back_and_keeps_off_obstacles():
    cfg, world, driver, segs, t, xy = _drive("rocky-1km", 400.0, seed=2)
    rc = cfg.tiled.route
    assert driver.legs_done >= 4  # it turned at several strategic waypoints
    assert revisits(t[::15], xy[::15], rc.revisit_radius_m, rc.revisit_after_s) == 0
    assert driver.planner.n_relaxed == 0
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert steps.sum() == pytest.approx(400.0, rel=0.05)
    # keeps off big rocks and deep crater interiors (pure pursuit may cut a plan's corner a little)
    box = (xy[:, 0].min() - 5, xy[:, 0].max() + 5, xy[:, 1].min() - 5, xy[:, 1].max() + 5)
    rocks = world.rocks_in(box, rc.avoid_rock_diameter_m)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xy[::3]).query(rocks.xy_m)
    assert np.all(d > 0.5 * rocks.diameter_m)  # never over a big rock's centre region
    cr = world.craters_near(box, reach_radii=1.0)
    deep = cr.subset(cr.diameter_m * depth_ratio(cr.degradation) > rc.avoid_crater_depth_m)
    if len(deep):
        dc, _ = cKDTree(xy[::3]).query(deep.xy_m)
        assert np.all(dc > 0.5 * deep.diameter_m * 0.8)
    # stops at the strategic waypoints: standstill segments of the configured length
    stops = [s for s in segs if s.kind == "stop"]
    assert len(stops) == driver.n_stops >= 3
    assert all(len(s.path.x_m) == round(rc.stop_s * cfg.sensors.imu.rate_hz) for s in stops)
    mean_speed = steps.sum() / t[-1]
    assert 0.07 < mean_speed < cfg.rover.cruise_speed_mps


def test_a_loop_comes_back_to_its_start():
    _cfg, _world, driver, _segs, _t, xy = _drive("sparse-5km", 260.0, seed=1, loop=True, stop_s=0.0)
    assert np.linalg.norm(xy[-1] - xy[0]) < 25.0
    assert np.linalg.norm(driver.route[-1] - driver.route[0]) < 1e-9

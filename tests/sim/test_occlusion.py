"""Ray-cast visibility: a rock hidden behind a big one is never detected."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim.config import StereoConfig
from sim.rocks import Rocks, icosphere
from sim.sensors.stereo import StereoCamera, simulate_stereo, visible_rocks
from sim.terrain import Heightmap
from sim.world import World


def _rock(x: float, y: float, diameter: float, height: float):
    v, f = icosphere(2)
    v = v * [diameter / 2, diameter / 2, height / 2] + [x, y, height / 2 - 0.05]
    return v, f


def _world(with_big: bool) -> World:
    flat = Heightmap(np.zeros((81, 81)), (-20, 20, -20, 20))
    meshes = [_rock(8.0, 0.0, 0.4, 0.3), _rock(6.0, 3.0, 0.4, 0.3)]  # hidden one, and a control
    if with_big:
        meshes.append(_rock(4.0, 0.0, 1.6, 1.6))
    return World("occlusion", flat, Rocks.from_meshes(meshes))


def _poses(n: int) -> np.ndarray:
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 2, 3] = 0.15
    return T


def test_camera_looks_forward_and_down():
    cam = StereoCamera.from_config(StereoConfig())
    z_axis = cam.T_base_cam[:3, 2]
    assert z_axis[0] > 0.9 and z_axis[2] < 0  # optical axis forward, tilted down
    assert cam.T_base_cam[:3, 0] @ [0, -1, 0] == pytest.approx(1.0)  # image x to the right


def test_rock_behind_a_big_rock_is_not_visible():
    cfg = StereoConfig()
    _, rk = visible_rocks(_world(True), _poses(1), cfg)
    assert set(rk.tolist()) == {1, 2}  # control and big rock
    _, rk = visible_rocks(_world(False), _poses(1), cfg)
    assert set(rk.tolist()) == {0, 1}  # without the big rock the small one shows


def test_occluded_rock_is_never_detected():
    cfg = dataclasses.replace(StereoConfig(), recall=1.0, precision=1.0)
    frames = simulate_stereo(_world(True), _poses(40), cfg, np.random.default_rng(0))
    found = np.concatenate(frames.rock)
    assert 0 not in found
    assert np.sum(found == 2) == 40 and np.sum(found == 1) == 40

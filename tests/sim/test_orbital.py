"""Orbital catalog presets and the shaded nadir image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim.config import OrbitalConfig, WorldGenConfig
from sim.errors import SimError
from sim.orbital_image import orbital_image
from sim.sensors.orbital import simulate_catalog
from sim.world import build_world


@pytest.fixture(scope="module")
def world():
    return build_world("my2020", seed=0, cfg=WorldGenConfig(resolution_m=0.4))


def test_published_preset_precision_recall_and_size_bias(world):
    out = simulate_catalog(world, OrbitalConfig(), np.random.default_rng(0))
    true = out.rock >= 0
    assert true.sum() / len(out.rock) == pytest.approx(0.44, abs=0.05)
    assert true.sum() / len(world.rocks) == pytest.approx(0.364, abs=0.05)
    # bigger rocks are found first
    found = np.zeros(len(world.rocks), dtype=bool)
    found[out.rock[true]] = True
    assert np.mean(found[world.rocks.size_m >= 0.5]) > 0.8
    assert np.mean(found[world.rocks.size_m < 0.15]) < 0.25
    err = out.catalog.xy_m[true] - world.rocks.xyz_m[out.rock[true], :2]
    assert np.std(err) == pytest.approx(0.05 * 2.0, rel=0.15)  # gsd 0.05 m x 2 px


def test_ideal_preset_finds_every_rock_above_the_visible_size(world):
    out = simulate_catalog(world, OrbitalConfig(preset="ideal"), np.random.default_rng(0))
    assert np.all(out.rock >= 0)
    visible = np.flatnonzero(world.rocks.size_m >= 3 * 0.05)
    assert set(out.rock.tolist()) == set(visible.tolist())
    err = out.catalog.xy_m - world.rocks.xyz_m[out.rock, :2]
    assert np.abs(err).max() < 0.05


def test_unknown_orbital_preset_raises(world):
    with pytest.raises(SimError, match="preset"):
        simulate_catalog(world, dataclasses.replace(OrbitalConfig(), preset="hirise"), np.random.default_rng(0))


def test_orbital_image_shows_rocks_and_shadows():
    w = build_world("my2022", seed=0, cfg=WorldGenConfig(resolution_m=0.3))
    img, extent = orbital_image(w, gsd_m=0.1)
    assert img.shape == (500, 500, 3) and img.dtype == np.uint8 and extent == w.extent
    big = np.argmax(w.rocks.size_m)
    x, y = w.rocks.xyz_m[big, :2]
    col, row = int((x - extent[0]) / 0.1), int((extent[3] - y) / 0.1)
    rock_px = img[row, col].astype(float)
    soil = np.median(img.reshape(-1, 3), axis=0)
    assert rock_px[0] - rock_px[2] < soil[0] - soil[2] - 20  # rocks are greyer than the red soil
    grey, _ = orbital_image(w, gsd_m=0.1, color=False)
    assert grey.ndim == 2
    low_sun, _ = orbital_image(w, gsd_m=0.1, sun_elevation_deg=10.0, color=False)
    def shadowed(g):
        return np.mean(g < 0.6 * np.median(g))

    assert shadowed(low_sun) > shadowed(grey) > 0  # longer shadows at low sun

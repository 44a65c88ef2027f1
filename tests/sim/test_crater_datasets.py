"""Cratered scenes and crater data sets: the heightfield shading agrees with the ray-cast nadir
renderer, labels follow their rules, the camera model's outputs, and seeded reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from sim.crater_datasets import (
    CraterSetConfig,
    crater_labels,
    crater_samples,
    orbital_sensor,
    signal_to_clutter,
)
from sim.crater_scene import SceneVariation, render_crater_scene, shade_heightfield, sun_shadows
from sim.craters import Craters, stamp_craters
from sim.render import Appearance, Lighting, Renderer
from sim.rocks import Rocks
from sim.terrain import Heightmap
from sim.world import World


def _crater_terrain(n: int = 96, d_m: float = 40.0) -> Heightmap:
    """A flat 1 m grid with one fresh crater of ``d_m`` at the centre and a smaller one beside it;
    nodes at pixel centres of an n x n image of extent (0, n, 0, n)."""
    hm = Heightmap(np.zeros((n, n)), (0.5, n - 0.5, 0.5, n - 0.5))
    craters = Craters(np.array([[n / 2, n / 2], [n / 2 + 30.0, n / 2 - 25.0]]), np.array([d_m, 12.0]),
                      np.array([0.0, 0.3]), np.array([0, 1]))
    return stamp_craters(hm, craters)


@pytest.mark.parametrize("elevation, azimuth", [(30.0, 135.0), (15.0, 0.0), (25.0, 260.0)])
def test_heightfield_shading_matches_the_ray_cast_renderer(elevation, azimuth):
    n = 96
    hm = _crater_terrain(n)
    app = Appearance(soil_albedo=0.5, texture_amplitude=0.0, noise_sigma=0.0, seed=0)
    light = Lighting(sun_elevation_deg=elevation, sun_azimuth_deg=azimuth, ambient=0.0)
    ours = shade_heightfield(hm, app, light, np.zeros(hm.z_m.shape, bool))
    world = World(name="t", terrain=hm, rocks=Rocks.from_meshes([]))
    ref = Renderer(world, app).nadir(1.0, light, extent=(0.0, n, 0.0, n)).image.astype(float) / 255.0
    inner = np.s_[2:-2, 2:-2]  # the renderer's edge pixels see the mesh border
    diff = np.abs(ours[inner] - ref[inner])
    assert np.mean(diff > 0.08) < 0.03, np.mean(diff > 0.08)
    shadow_ours, shadow_ref = ours[inner] < 0.01, ref[inner] < 0.01
    assert shadow_ref.sum() > 20  # the bowl casts a shadow
    assert abs(int(shadow_ours.sum()) - int(shadow_ref.sum())) <= 0.1 * shadow_ref.sum() + 5
    assert np.mean(shadow_ours != shadow_ref) < 0.01


def test_sun_shadows_of_a_step():
    # a 10 m scarp rising from x = 48 m to 52 m: with the sun at 45 degrees in the +x direction
    # its crest shades the 10 m in front of it (to x = 42 m), the scarp face included
    z = np.tile(np.clip((np.arange(100.0) - 48.0) * 2.5, 0.0, 10.0), (20, 1))
    lit = sun_shadows(z, 1.0, Lighting(sun_elevation_deg=45.0, sun_azimuth_deg=0.0))
    assert lit[:, 54:].all() and lit[:, :42].all()  # the crest itself is grazed
    assert not lit[5:15, 43:51].any()
    lit_w = sun_shadows(z, 1.0, Lighting(sun_elevation_deg=45.0, sun_azimuth_deg=180.0))
    assert lit_w[2:-2, 2:-2].all()  # sun from -x: nothing blocks it


def test_labels_positive_ignore_and_outside():
    c = np.array([[10.0, 10.0], [50.0, 50.0], [60.0, 5.0], [-3.0, 30.0], [-30.0, 30.0], [20.0, 70.0]])
    d = np.array([3.0, 12.0, 9.0, 10.0, 10.0, 20.0])
    vis = np.array([True, True, False, True, True, True])
    lab = crater_labels(c, d, vis, (64, 80))
    # (10, 10) too small -> ignore; (50, 50) positive; (60, 5) hidden -> ignore; (-3, 30) centred
    # outside but reaching in -> ignore; (-30, 30) far outside -> dropped; (20, 70) outside the 64 rows
    # but reaching in -> ignore
    assert len(lab) == 5
    assert lab.ignore.tolist() == [True, False, True, True, True]
    pc, pd = lab.positives
    assert np.allclose(pc, [[50.0, 50.0]]) and np.allclose(pd, [12.0])
    half = lab.scaled(0.5, (10.0, 10.0))
    assert np.allclose(half.centres_px[1], [20.0, 20.0]) and np.allclose(half.diameters_px[1], 6.0)


def test_sensor_outputs_and_seeding():
    grey = np.random.default_rng(0).uniform(0.2, 0.8, (64, 64)).astype(np.float32)
    kinds = {orbital_sensor(grey, np.random.default_rng(k)).dtype for k in range(40)}
    assert kinds == {np.dtype(np.uint8), np.dtype(np.uint16)}
    a = orbital_sensor(grey, np.random.default_rng(3))
    b = orbital_sensor(grey, np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_seeded_scene_is_reproducible_and_labelled():
    var = SceneVariation(size_px=128)
    a = render_crater_scene(var, np.random.default_rng(5))
    b = render_crater_scene(var, np.random.default_rng(5))
    assert np.array_equal(a.grey, b.grey) and np.array_equal(a.diameters_px, b.diameters_px)
    assert a.grey.shape == (128, 128) and 0.0 <= a.grey.min() and a.grey.max() <= 1.0
    s = next(crater_samples(1, 0, "eval", CraterSetConfig(scene=var)))
    assert s.image.shape == (128, 128) and len(s.labels) > 0
    centres, diam = s.labels.positives
    assert np.all(diam >= 4.0) and np.all((centres >= 0) & (centres < 128))


def _crater_signal(n: int, centre: tuple[float, float], d: float) -> np.ndarray:
    """A lit bowl's pattern: bright on one side of the disc, dark on the other (n x n, amplitude 1)."""
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    u, v = (xx - centre[0]) / (0.5 * d), (yy - centre[1]) / (0.5 * d)
    return np.where(np.hypot(u, v) <= 1.0, u, 0.0).astype(np.float32)


def test_signal_to_clutter_scales_with_the_signal_and_the_clutter():
    n, d = 128, 16.0
    noise = np.random.default_rng(0).standard_normal((n, n)).astype(np.float32)
    pattern = _crater_signal(n, (40.0, 40.0), d)
    centres, diam = np.array([[40.0, 40.0], [100.0, 90.0], [64.0, 64.0]]), np.array([d, d, 3.0])
    ground = 0.5 + 0.01 * noise
    r1 = signal_to_clutter(ground + 0.05 * pattern, ground, centres, diam)
    r2 = signal_to_clutter(ground + 0.10 * pattern, ground, centres, diam)
    assert r1[0] > 1.0 and r2[0] == pytest.approx(2.0 * r1[0], rel=1e-4)  # the band-pass is linear
    assert r1[1] == pytest.approx(0.0, abs=1e-6)  # no signal where there is no crater
    assert np.isnan(r1[2])  # under 4 px: not measured
    rough = 0.5 + 0.05 * noise  # five times the clutter, the same crater
    r3 = signal_to_clutter(rough + 0.05 * pattern, rough, centres, diam)
    assert r3[0] == pytest.approx(r1[0] / 5.0, rel=1e-3)
    # integer images are measured in their full scale: the same ratio from a 16-bit image
    q = lambda x: np.rint(np.clip(x, 0, 1) * 65535).astype(np.uint16)
    r4 = signal_to_clutter(q(ground + 0.05 * pattern), q(ground), centres, diam)
    assert r4[0] == pytest.approx(r1[0], rel=0.02)
    with pytest.raises(ValueError, match="must be the same"):
        signal_to_clutter(ground, ground[:64], centres, diam)


def test_samples_with_the_signal_to_clutter_ratio_are_the_same_images():
    cfg = CraterSetConfig(scene=SceneVariation(size_px=256))
    plain = next(crater_samples(1, 3, "eval", cfg))
    s = next(crater_samples(1, 3, "eval", cfg, scr=True))
    assert np.array_equal(plain.image, s.image) and np.array_equal(plain.labels.diameters_px, s.labels.diameters_px)
    assert plain.scr is None and s.scr.shape == s.labels.diameters_px.shape
    big = s.labels.diameters_px >= 4.0
    assert np.all(np.isnan(s.scr[~big])) and np.all(np.isfinite(s.scr[big]) & (s.scr[big] >= 0.0))
    # the ground without craters: the same image where no crater reaches
    g = s.scene.grey_without_craters
    assert g.shape == s.scene.grey.shape
    yy, xx = np.mgrid[0:256, 0:256] + 0.5
    far = np.ones((256, 256), bool)
    for (cx, cy), dd in zip(s.scene.centres_px, s.scene.diameters_px):
        far &= np.hypot(xx - cx, yy - cy) > 1.5 * dd + 3.0
    assert far.sum() > 100
    assert np.median(np.abs(g[far] - s.scene.grey[far])) < 0.02 * np.median(s.scene.grey)
    assert np.median(np.abs(g[~far] - s.scene.grey[~far])) > 0.0  # and the craters' own pixels differ


@pytest.mark.parametrize("size", [64, 136, 1024])
def test_relief_at_scales_is_finite_down_to_the_smallest_level(size):
    """Every pyramid level a scene reaches gets a finite rms relief, also the 8-px level of a
    1024 px scene (an empty interior once made it NaN, and a NaN level hides every crater of that
    size); white noise has its relief in the finest band."""
    import warnings

    from sim.crater_scene import relief_at_scales

    z = np.random.default_rng(3).standard_normal((size, size))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        relief = relief_at_scales(z, 1)
    assert np.all(np.isfinite(relief))
    reached = relief[relief > 0]
    sizes = [size]
    while (sizes[-1] + 1) // 2 >= 8:  # cv2.pyrDown halves, rounding up
        sizes.append((sizes[-1] + 1) // 2)
    assert len(reached) == len(sizes)
    assert reached[0] == reached.max()

"""Renderer geometry: rocks appear where they project, shadows fall away from the sun, the right
view is the left shifted by the disparity, and box labels come from the instance image."""

from __future__ import annotations

import numpy as np
import pytest

from sim.datasets import box_labels, rover_pose
from sim.render import Appearance, Lighting, PinholeCamera, Renderer, RenderError
from sim.rocks import Rocks, icosphere
from sim.terrain import Heightmap
from sim.world import World

FLAT = Appearance(texture_amplitude=0.0, noise_sigma=0.0, rock_albedo_spread=0.0)


def _world(rocks_xy_d: list[tuple[float, float, float]], size_m: float = 12.0) -> World:
    """Flat ground at z = 0 with round rocks (centre x, y, diameter) resting on it."""
    v, f = icosphere(2)
    meshes = []
    for x, y, d in rocks_xy_d:
        meshes.append((v * (d / 2) + np.array([x, y, d / 2]), f))
    s = size_m / 2
    terrain = Heightmap(np.zeros((41, 41)), (-s, s, -s, s))
    return World("test", terrain, Rocks.from_meshes(meshes))


def test_nadir_rock_appears_at_its_pixel():
    world = _world([(1.3, -2.1, 0.6), (-3.0, 2.5, 0.4)])
    r = Renderer(world, FLAT).nadir(0.05, Lighting(sun_elevation_deg=60.0))
    assert r.image.shape == (240, 240) and r.image.dtype == np.uint8
    for k in range(2):
        rows, cols = np.nonzero(r.instance == k)
        centroid_uv = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        expect = r.world_to_pixel(world.rocks.xyz_m[k, :2])[0]
        assert np.linalg.norm(centroid_uv - expect) < 0.5
        # the footprint of a sphere of diameter d is a disc of d / gsd pixels across
        assert abs(2 * np.sqrt(len(rows) / np.pi) - world.rocks.size_m[k] / 0.05) < 1.5
    assert np.allclose(r.pixel_to_world(r.world_to_pixel(world.rocks.xyz_m[:, :2])), world.rocks.xyz_m[:, :2])


@pytest.mark.parametrize("azimuth_deg", [0.0, 135.0, 250.0])
def test_shadows_fall_away_from_the_sun(azimuth_deg):
    world = _world([(0.0, 0.0, 1.0)], size_m=8.0)
    light = Lighting(sun_elevation_deg=25.0, sun_azimuth_deg=azimuth_deg, ambient=0.2)
    r = Renderer(world, FLAT).nadir(0.04, light)
    soil = r.instance < 0
    bright = np.median(r.image[soil])
    rows, cols = np.nonzero(soil & (r.image < 0.6 * bright))
    assert len(rows) > 100  # a 1 m rock under a 25-degree sun casts a long shadow
    xy = r.pixel_to_world(np.column_stack([cols + 0.5, rows + 0.5]))
    direction = xy.mean(axis=0) / np.linalg.norm(xy.mean(axis=0))
    sun_xy = light.sun_dir()[:2] / np.linalg.norm(light.sun_dir()[:2])
    assert direction @ sun_xy < -0.95
    # length: a 1 m sphere's shadow reaches about d / tan(elevation) past the rock's centre
    reach = np.max(-(xy @ sun_xy))
    assert 1.2 < reach < 1.0 / np.tan(np.deg2rad(25.0)) + 0.8


def test_pinhole_and_stereo_geometry():
    world = _world([(4.0, 0.5, 0.5)])
    cam = PinholeCamera.from_fov(320, 180, 80.0)
    T_world_base = rover_pose(world, np.array([0.0, 0.0]), 0.0)
    R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes in base_link
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = R0
    T_base_cam[:3, 3] = (0.0, 0.0, 0.6)
    T_wc = T_world_base @ T_base_cam
    baseline = 0.2
    sr = Renderer(world, FLAT).stereo(T_wc, cam, baseline, Lighting(sun_elevation_deg=50.0))
    centre_c = (world.rocks.xyz_m[0] - T_wc[:3, 3]) @ T_wc[:3, :3]
    uv = cam.project(centre_c)[0]
    rows, cols = np.nonzero(sr.instance_left == 0)
    assert np.linalg.norm([cols.mean() + 0.5 - uv[0], rows.mean() + 0.5 - uv[1]]) < 2.0
    # depth at the rock's central pixel: front surface, one radius before the centre
    z = sr.depth_left_m[int(uv[1]), int(uv[0])]
    assert abs(z - (centre_c[2] - 0.25)) < 0.05
    # the right view sees the rock shifted left by the disparity f b / z
    rows_r, cols_r = np.nonzero(sr.instance_right == 0)
    shift = cols.mean() - cols_r.mean()
    assert abs(shift - cam.f_px * baseline / centre_c[2]) < 1.0
    assert abs(rows.mean() - rows_r.mean()) < 0.5


def test_stereo_right_view_matches_its_own_pinhole_render():
    """The right view's shared cast and reused shadow tests give the image a separate render of
    the right camera gives (low sun, several rocks casting shadows onto each other)."""
    world = _world([(3.0, 0.4, 0.6), (3.6, -0.3, 0.5), (2.5, -0.9, 0.3), (5.0, 1.2, 0.8)])
    cam = PinholeCamera.from_fov(160, 90, 80.0)
    T_wc = rover_pose(world, np.array([0.0, 0.0]), 0.0) @ np.array(
        [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.8], [0.0, 0.0, 0.0, 1.0]])
    light = Lighting(sun_elevation_deg=20.0, sun_azimuth_deg=200.0)
    r = Renderer(world, FLAT)
    sr = r.stereo(T_wc, cam, 0.3, light)
    T_right = T_wc.copy()
    T_right[:3, 3] += 0.3 * T_wc[:3, 0]
    img_r, inst_r, _ = r.pinhole(T_right, cam, light)
    img_l, inst_l, depth_l = r.pinhole(T_wc, cam, light)
    assert np.array_equal(inst_r, sr.instance_right) and np.array_equal(inst_l, sr.instance_left)
    assert np.abs(img_l.astype(int) - sr.left).max() <= 1
    # a reused shadow flag may differ right at a shadow edge (a sub-pixel apart): rare
    assert np.mean(np.abs(img_r.astype(int) - sr.right) > 1) < 5e-4
    assert np.allclose(depth_l, sr.depth_left_m, rtol=1e-5)
    # the scene is not trivial: rocks in view, shadowed soil in both images
    assert len(np.unique(sr.instance_right)) >= 4
    soil = sr.instance_right < 0
    assert np.sum(soil & (sr.right < 0.6 * np.median(sr.right[soil]))) > 20


def test_box_labels_and_ignore():
    inst = -np.ones((20, 30), dtype=np.int32)
    inst[2:8, 3:10] = 4
    inst[15:17, 20:21] = 1  # too small
    lab = box_labels(inst, min_area_px=10, min_side_px=2)
    order = np.argsort(lab.rock)
    assert list(lab.rock[order]) == [1, 4]
    assert np.allclose(lab.boxes_xyxy[order][1], [3, 2, 10, 8])
    assert list(lab.ignore[order]) == [True, False]
    assert lab.positives.shape == (1, 4)


def test_bad_requests_are_rejected():
    world = _world([(0.0, 0.0, 0.5)])
    r = Renderer(world, FLAT)
    with pytest.raises(RenderError, match="gsd_m"):
        r.nadir(0.0)
    with pytest.raises(RenderError, match="sun_elevation"):
        r.nadir(0.1, Lighting(sun_elevation_deg=-5.0))
    with pytest.raises(RenderError, match="4x4"):
        r.stereo(np.eye(3), PinholeCamera.from_fov(64, 48, 60.0), 0.1)


def test_raycast_scene_first_hits_and_occlusion():
    """The scene's own queries: distance, rock id and a normal facing the ray; misses; any-hit
    shadow tests that stop at ``t_far_m``."""
    world = _world([(1.0, 0.0, 0.5)])
    scene = world.raycast_scene()
    rays = np.array([[1.0, 0.0, 3.0, 0.0, 0.0, -1.0],  # onto the rock's top
                     [-3.0, 2.0, 3.0, 0.0, 0.0, -1.0],  # onto flat soil
                     [0.0, 0.0, 3.0, 0.0, 0.0, 1.0]], np.float32)  # up into the sky
    h = scene.first_hits(rays)
    assert h.t_m.dtype == np.float32 and list(h.hit) == [True, True, False]
    assert h.t_m[0] == pytest.approx(3.0 - 0.5, abs=0.02) and h.t_m[1] == pytest.approx(3.0, abs=1e-5)
    assert list(h.rock) == [0, -1, -1]
    assert np.all(h.normal[:2] @ np.array([0.0, 0.0, -1.0]) < 0)  # turned towards the ray origin
    t64, rock64, _ = scene.cast(rays)
    assert t64.dtype == np.float64 and np.array_equal(rock64, h.rock)
    assert 0.0 < scene.z_bottom_m + 1e-9 and scene.z_top_m == pytest.approx(0.5, abs=0.02)
    # sideways past the rock: blocked, unless the test stops before it
    side = np.array([[-1.0, 0.0, 0.25, 1.0, 0.0, 0.0]], np.float32)
    assert not scene.unoccluded(side)[0] and scene.unoccluded(side, t_far_m=1.0)[0]


def test_sampled_shadows_agree_with_one_ray_per_pixel():
    """The checkerboard shadow sampling (about half the rays) gives the flags of a shadow ray for
    every sun-facing pixel, shadow edges and rock silhouettes included."""
    from sim.render.camera import pixel_grid, view_rays
    from sim.render.shading import cos_to_sun
    from sim.render.shadows import SunTest, sampled_sunlit

    world = _world([(3.0, 0.4, 0.6), (3.6, -0.3, 0.5), (2.5, -0.9, 0.3), (5.0, 1.2, 0.8), (4.2, 0.1, 0.15)])
    cam = PinholeCamera.from_fov(200, 120, 80.0)
    T_wc = rover_pose(world, np.array([0.0, 0.0]), 0.0) @ np.array(
        [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.8], [0.0, 0.0, 0.0, 1.0]])
    grid = pixel_grid(cam)
    rays = view_rays(T_wc[None, :3, 3], grid.dirs_cam @ T_wc[:3, :3].T.astype(np.float32))
    scene = world.raycast_scene()
    hits = scene.first_hits(rays)
    for elevation, azimuth in ((15.0, 90.0), (30.0, 300.0)):
        sun = Lighting(sun_elevation_deg=elevation, sun_azimuth_deg=azimuth).sun_dir().astype(np.float32)
        facing = cos_to_sun(hits.normal, sun) > 0
        test = SunTest(scene, rays, hits, sun)
        every = np.zeros(len(rays), dtype=bool)
        every[facing] = test.sunlit(np.flatnonzero(facing))
        test.n_rays = 0
        shape = (cam.height_px, cam.width_px)
        lit = sampled_sunlit(test.sunlit, facing.reshape(shape), hits.rock.reshape(shape),
                             (1.0 / (hits.t_m * grid.z_cam)).reshape(shape))
        assert np.array_equal(lit, every)
        assert 0.45 * facing.sum() < test.n_rays < 0.7 * facing.sum()
        assert 0.05 * facing.sum() < np.sum(facing & ~every)  # the scene has shadows to get right

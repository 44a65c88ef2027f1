"""Stereo triangulation: exact on exact disparities, covariance from the disparity error model,
and rock centres recovered from a rendered pair within that model (both disparity methods)."""

from __future__ import annotations

import numpy as np
import pytest

from reloc.detector import Detections
from reloc.stereo import StereoError, StereoRig, TriangulationConfig, match_detections, rock_points, triangulate
from sim.datasets import box_labels, rover_pose
from sim.render import Appearance, Lighting, PinholeCamera, Renderer
from sim.rocks import generate_rocks
from sim.terrain import fractal_heightmap
from sim.world import World

CHI2_3_99 = 11.34


def test_triangulate_exact_and_error_model(rng):
    rig = StereoRig(f_px=400.0, cx_px=320.0, cy_px=180.0, baseline_m=0.12)
    pts = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-0.5, 1, 50), rng.uniform(1, 12, 50)])
    uv = np.column_stack([rig.f_px * pts[:, 0] / pts[:, 2] + rig.cx_px, rig.f_px * pts[:, 1] / pts[:, 2] + rig.cy_px])
    d = rig.f_px * rig.baseline_m / pts[:, 2]
    xyz, cov = triangulate(uv, d, rig, sigma_pixel_px=1.0, sigma_disparity_px=0.3)
    assert np.allclose(xyz, pts)
    sigma_z = pts[:, 2] ** 2 * 0.3 / (rig.f_px * rig.baseline_m)
    assert np.allclose(np.sqrt(cov[:, 2, 2]), sigma_z)
    # Monte Carlo: perturbed pixels/disparities scatter as the covariance says
    k = 7
    n = 4000
    uvn = uv[k] + rng.normal(0, 1.0, (n, 2))
    dn = d[k] + rng.normal(0, 0.3, n)
    xn, _ = triangulate(uvn, dn[dn > 0], rig, 1.0, 0.3) if np.all(dn > 0) else (None, None)
    emp = np.cov(xn.T)
    assert np.allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(cov[k])), rtol=0.15)
    with pytest.raises(StereoError):
        triangulate(uv[:1], np.array([0.0]), rig, 1.0, 0.3)


def test_match_detections_pairs_rows_and_sizes():
    left = Detections(np.array([[100, 50, 120, 70], [300, 200, 330, 220]], np.float32), np.ones(2, np.float32), np.zeros(2, np.int64))
    right = Detections(np.array([[280, 201, 310, 221], [90, 50, 110, 70], [95, 120, 115, 140]], np.float32), np.ones(3, np.float32), np.zeros(3, np.int64))
    li, ri = match_detections(left, right)
    assert dict(zip(li.tolist(), ri.tolist())) == {0: 1, 1: 0}


def _rock_field() -> World:
    rng = np.random.default_rng(4)
    terrain = fractal_heightmap((-15, 15, -15, 15), 0.4, 0.15, rng)
    rocks = generate_rocks(terrain, 220, rng, d_min=0.25, d_max=0.9, alpha=1.5)
    return World("stereo-test", terrain, rocks)


@pytest.mark.parametrize("method", ["sgbm", "match"])
def test_rendered_pair_recovers_rock_centres(method):
    world = _rock_field()
    cam = PinholeCamera.from_fov(640, 360, 80.0)
    R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    th = np.deg2rad(20.0)
    Ry = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = Ry @ R0
    T_base_cam[:3, 3] = (0.15, 0.0, 0.85)
    T_wc = rover_pose(world, np.array([-6.0, 0.0]), 0.1) @ T_base_cam
    sr = Renderer(world, Appearance(seed=3)).stereo(T_wc, cam, 0.12, Lighting(sun_elevation_deg=40.0))
    lab = box_labels(sr.instance_left, 60, 6)
    keep = ~lab.ignore
    # true rocks within 8 m in front of the camera, boxes taken from the instance image
    centres_c = (world.rocks.xyz_m[lab.rock] - T_wc[:3, 3]) @ T_wc[:3, :3]
    keep &= centres_c[:, 2] < 8.0
    assert keep.sum() >= 8
    left = Detections(lab.boxes_xyxy[keep], np.ones(keep.sum(), np.float32), np.zeros(keep.sum(), np.int64))
    right = None
    if method == "match":
        lab_r = box_labels(sr.instance_right, 60, 6)
        right = Detections(lab_r.boxes_xyxy, np.ones(len(lab_r.rock), np.float32), np.zeros(len(lab_r.rock), np.int64))
    rig = StereoRig(cam.f_px, cam.cx_px, cam.cy_px, 0.12)
    rp = rock_points(sr.left, sr.right, left, rig, TriangulationConfig(method=method), right)
    assert len(rp) >= 0.8 * keep.sum()
    truth = centres_c[keep][rp.index]
    err = rp.xyz_cam_m - truth
    m2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(rp.cov_cam_m2), err)
    # the error model covers the errors: most inside the 99 % ellipsoid, and not grossly loose
    assert np.mean(m2 < CHI2_3_99) >= 0.85
    assert np.median(m2) > 0.1
    depth_sigma = np.sqrt(rp.cov_cam_m2[:, 2, 2])
    assert np.median(np.abs(err[:, 2]) / depth_sigma) < 2.0
    size_true = world.rocks.size_m[lab.rock[keep][rp.index]]
    assert 0.7 < np.median(rp.size_m / size_true) < 1.4
    with pytest.raises(StereoError, match="method"):
        rock_points(sr.left, sr.right, left, rig, TriangulationConfig(method="bogus"))
    with pytest.raises(StereoError, match="one size"):
        rock_points(sr.left, sr.right[:-1], left, rig)

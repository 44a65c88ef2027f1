"""Pinhole views: one camera, or a rectified stereo pair (right = left + baseline along the
optical x axis) rendered from one primary ray cast for both views."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.render.camera import PinholeCamera, checked_pose, pixel_grid, view_rays, world_dirs
from sim.render.config import Lighting, RenderError
from sim.render.shading import Shader, cos_to_sun, shaded_grey, to_uint8
from sim.render.shadows import SunTest, right_from_left, sampled_sunlit
from sim.world import RaycastScene


@dataclass(frozen=True)
class StereoRender:
    """Rectified stereo pair: ``left``/``right`` (H, W) uint8, ``instance_left``/``instance_right``
    (H, W) int32 rock rows (-1: none), ``depth_left_m`` (H, W) optical z of the left hits (inf:
    sky), ``T_world_left`` (4, 4) the left optical frame, ``baseline_m`` (right = left + b x)."""

    left: np.ndarray
    right: np.ndarray
    instance_left: np.ndarray
    instance_right: np.ndarray
    depth_left_m: np.ndarray
    T_world_left: np.ndarray
    camera: PinholeCamera
    baseline_m: float


@dataclass(frozen=True)
class Views:
    """V pinhole views of one camera, flat row-major per view: ``grey`` (V, H*W) float32 in
    [0, 1], ``instance`` (V, H*W) int32 rock rows, ``depth_m`` (V, H*W) float32 optical z (inf:
    sky), ``shadow_rays`` cast."""

    grey: np.ndarray
    instance: np.ndarray
    depth_m: np.ndarray
    shadow_rays: int


def render_views(scene: RaycastScene, shader: Shader, T_world_cam: np.ndarray, camera: PinholeCamera,
                 lighting: Lighting, baseline_m: float | None = None, nthreads: int = 0) -> Views:
    """Grey levels, rock ids and depth of the camera at ``T_world_cam`` (4, 4, optical frame) and,
    with ``baseline_m``, of a second one that far along its +x (see :mod:`sim.render.shadows` for
    which shadow rays are cast)."""
    T = np.asarray(T_world_cam, dtype=float)
    R = T[:3, :3].astype(np.float32)
    grid = pixel_grid(camera)
    dirs = world_dirs(camera, R)
    origins = [T[:3, 3].astype(np.float32)]
    if baseline_m is not None:
        origins.append(origins[0] + np.float32(baseline_m) * R[:, 0])
    origins = np.array(origins)
    V, n, H, W = len(origins), len(dirs), camera.height_px, camera.width_px
    rays = view_rays(origins, dirs)
    hits = scene.first_hits(rays, nthreads)
    hit = hits.hit
    sun = lighting.sun_dir().astype(np.float32)
    cos_sun = cos_to_sun(hits.normal, sun)
    facing = cos_sun > 0  # a miss has a zero normal: never facing
    depth = hits.t_m.reshape(V, n) * grid.z_cam  # inf on a miss
    test = SunTest(scene, rays, hits, sun, nthreads)
    lit = np.empty(V * n, dtype=bool)
    inv_depth = np.float32(1.0) / depth[0]
    lit[:n] = sampled_sunlit(test.sunlit, facing[:n].reshape(H, W), hits.rock[:n].reshape(H, W), inv_depth.reshape(H, W))
    if V == 2:
        lit_right, todo = right_from_left(lit[:n].reshape(H, W), depth[0], facing[n:], depth[1], grid.col,
                                          camera.f_px * float(baseline_m))
        lit_right[todo] = test.sunlit(n + todo)
        lit[n:] = lit_right
    t = np.where(hit, hits.t_m, np.float32(0.0)).reshape(V, n)
    x, y = t * dirs[:, 0], t * dirs[:, 1]
    x += origins[:, 0:1]
    y += origins[:, 1:2]
    grey = shaded_grey(shader, lighting, sun, hit, hits.rock, x.ravel(), y.ravel(), cos_sun, lit)
    return Views(grey.reshape(V, n), hits.rock.reshape(V, n), depth, test.n_rays)


def render_pinhole(scene: RaycastScene, shader: Shader, T_world_cam: np.ndarray, camera: PinholeCamera,
                   lighting: Lighting, rng: np.random.Generator | None = None, nthreads: int = 0):
    """One view: image (H, W) uint8, instance (H, W) int32 rock rows (-1: none), optical depth
    (H, W) metres (inf: sky); noise from ``rng`` (default seeded by the appearance)."""
    T = checked_pose(T_world_cam, "T_world_cam")
    v = render_views(scene, shader, T, camera, lighting, None, nthreads)
    shape = (camera.height_px, camera.width_px)
    return to_uint8(v.grey[0].reshape(shape), shader.app, rng), v.instance[0].reshape(shape), v.depth_m[0].reshape(shape)


def render_stereo_pair(scene: RaycastScene, shader: Shader, T_world_left: np.ndarray, camera: PinholeCamera,
                       baseline_m: float, lighting: Lighting, rng: np.random.Generator | None = None,
                       nthreads: int = 0) -> StereoRender:
    """The pair of :class:`StereoRender`; both images' noise from ``rng`` (default seeded by the
    appearance), left first."""
    T = checked_pose(T_world_left, "T_world_left")
    if not baseline_m > 0:
        raise RenderError(f"baseline_m must be > 0, got {baseline_m}")
    v = render_views(scene, shader, T, camera, lighting, float(baseline_m), nthreads)
    shape = (camera.height_px, camera.width_px)
    rng = rng if rng is not None else np.random.default_rng([shader.app.seed, 13])
    left = to_uint8(v.grey[0].reshape(shape), shader.app, rng)
    right = to_uint8(v.grey[1].reshape(shape), shader.app, rng)
    return StereoRender(left, right, v.instance[0].reshape(shape), v.instance[1].reshape(shape),
                        v.depth_m[0].reshape(shape), T, camera, float(baseline_m))

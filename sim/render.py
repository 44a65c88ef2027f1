"""Image renderer: a nadir orthographic "orbital" view and the rover's rectified stereo pair.

Both views ray-cast the world's terrain and rock meshes with open3d's ``RaycastingScene`` (CPU),
shade the hit points with a Lambertian sun plus ambient light, darken points whose ray towards the
sun is blocked (cast shadows, the cue nadir rock counting relies on), and return an exact
per-pixel rock instance id (the row in ``world.rocks``, -1 for terrain or sky) from which box
labels are made. Soil albedo carries a seeded value-noise texture and each rock its own albedo,
so that a detector has to learn shape and shadow rather than a single rock colour.

Image conventions: nadir row 0 is the +y edge of the extent and column 0 its -x edge, pixel
centres at half-integer offsets; pinhole images use the optical frame (z forward, x right,
y down), pixel (u, v) = (f x / z + cx, f y / z + cy) with pixel centres at integers + 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

from sim.errors import SimError
from sim.world import World


class RenderError(SimError, ValueError):
    """A render request is invalid (empty extent, bad camera, bad lighting)."""


@dataclass(frozen=True)
class Lighting:
    """Sun direction (azimuth counted from +x towards +y) and the ambient share of the light."""

    sun_elevation_deg: float = 30.0
    sun_azimuth_deg: float = 135.0
    ambient: float = 0.22

    def sun_dir(self) -> np.ndarray:
        """Unit vector (3,) from the ground towards the sun, world frame."""
        if not 0.0 < self.sun_elevation_deg <= 90.0:
            raise RenderError(f"sun_elevation_deg must be in (0, 90], got {self.sun_elevation_deg}")
        el, az = np.deg2rad(self.sun_elevation_deg), np.deg2rad(self.sun_azimuth_deg)
        return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


@dataclass(frozen=True)
class Appearance:
    """Albedos (0..1), soil texture and sensor noise; ``seed`` fixes texture and rock albedos."""

    soil_albedo: float = 0.62
    rock_albedo: float = 0.50
    rock_albedo_spread: float = 0.18  # relative per-rock albedo spread
    texture_amplitude: float = 0.12  # relative soil albedo variation
    texture_scale_m: float = 0.4
    sky_level: float = 0.55
    noise_sigma: float = 2.0  # grey levels of additive sensor noise
    blur_sigma_px: float = 0.0  # optical blur (nadir imagery)
    seed: int = 0


class _Shader:
    """Texture and per-rock albedos of one (world, appearance) pair."""

    def __init__(self, world: World, app: Appearance) -> None:
        rng = np.random.default_rng([app.seed, 7])
        xmin, xmax, ymin, ymax = world.extent
        cell = max(app.texture_scale_m / 2.0, 1e-3)
        nx = int((xmax - xmin) / cell) + 3
        ny = int((ymax - ymin) / cell) + 3
        # fine speckle plus a coarser mottling (weighted up: smoothing shrinks its spread)
        grid = gaussian_filter(rng.standard_normal((ny, nx)), 1.0)
        grid += 1.5 * gaussian_filter(rng.standard_normal((ny, nx)), 4.0)
        self._tex = grid / (grid.std() + 1e-12)
        self._origin = (xmin - cell, ymin - cell)
        self._cell = cell
        n = len(world.rocks)
        self._rock_albedo = app.rock_albedo * np.exp(app.rock_albedo_spread * rng.standard_normal(n))
        self.app = app

    def albedo(self, xyz: np.ndarray, rock: np.ndarray) -> np.ndarray:
        """Albedo (N,) of surface points ``xyz`` (N, 3) owned by ``rock`` (N,) (-1: soil)."""
        fx = (xyz[:, 0] - self._origin[0]) / self._cell
        fy = (xyz[:, 1] - self._origin[1]) / self._cell
        tex = map_coordinates(self._tex, [fy, fx], order=1, mode="nearest")
        soil = self.app.soil_albedo * (1.0 + self.app.texture_amplitude * tex)
        out = soil
        on_rock = rock >= 0
        if np.any(on_rock):
            out = np.where(on_rock, self._rock_albedo[np.maximum(rock, 0)] * (1.0 + 0.3 * self.app.texture_amplitude * tex), soil)
        return out


def _hits(world: World, rays: np.ndarray):
    """Cast ``rays`` (N, 6): hit mask, rock row (-1: none), distance, point (N, 3) and the unit
    normal (N, 3) turned towards the viewer."""
    t_hit, rock, normal = world.raycast_scene().cast(rays)
    hit = np.isfinite(t_hit)
    d = rays[:, 3:6]
    normal *= -np.sign(np.einsum("ij,ij->i", normal, d) + 1e-12)[:, None]
    p = rays[:, :3] + d * np.where(hit, t_hit, 0.0)[:, None]
    return hit, np.where(hit, rock, -1), t_hit, p, normal


def _sunlit(world: World, p: np.ndarray, normal: np.ndarray, sun: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """Boolean (N,): surface points ``p`` (N, 3) flagged in ``todo`` that see the sun."""
    lit = np.zeros(len(p), dtype=bool)
    idx = np.flatnonzero(todo)
    if len(idx):
        shadow = np.hstack([p[idx] + 0.01 * normal[idx], np.broadcast_to(sun, (len(idx), 3))])
        t_sh, _, _ = world.raycast_scene().cast(shadow)
        lit[idx] = ~np.isfinite(t_sh)
    return lit


def _grey(shader: "_Shader", lighting: Lighting, hit, rock, p, normal, lit) -> np.ndarray:
    """Grey level (N,) in [0, 1]: albedo x (ambient + direct sun), the sky level on a miss."""
    sun = lighting.sun_dir()
    lambert = np.clip(normal @ sun, 0.0, 1.0)
    light = lighting.ambient + (1.0 - lighting.ambient) * lambert * lit / max(sun[2], 0.5)
    grey = np.full(len(p), shader.app.sky_level)
    grey[hit] = shader.albedo(p[hit], rock[hit]) * light[hit]
    return np.clip(grey, 0.0, 1.0)


def _to_uint8(grey: np.ndarray, app: Appearance, rng: np.random.Generator | None) -> np.ndarray:
    img = (255.0 * grey).astype(np.float32)
    if app.blur_sigma_px > 0:
        img = gaussian_filter(img, app.blur_sigma_px)
    if app.noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng([app.seed, 11])
        img = img + np.float32(app.noise_sigma) * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class NadirRender:
    """Nadir image: ``image`` (H, W) uint8 grey, ``instance`` (H, W) int32 rock row (-1: soil),
    ``extent`` (xmin, xmax, ymin, ymax) world metres, ``gsd_m`` metres per pixel."""

    image: np.ndarray
    instance: np.ndarray
    extent: tuple[float, float, float, float]
    gsd_m: float

    def pixel_to_world(self, uv: np.ndarray) -> np.ndarray:
        """World xy (N, 2) of continuous pixel coordinates ``uv`` (N, 2) (column, row)."""
        uv = np.reshape(uv, (-1, 2))
        return np.column_stack([self.extent[0] + uv[:, 0] * self.gsd_m, self.extent[3] - uv[:, 1] * self.gsd_m])

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates (N, 2) (column, row) of world points ``xy`` (N, 2)."""
        xy = np.reshape(xy, (-1, 2))
        return np.column_stack([(xy[:, 0] - self.extent[0]) / self.gsd_m, (self.extent[3] - xy[:, 1]) / self.gsd_m])


class Renderer:
    """Renders one world under one appearance (texture and rock albedos are built once)."""

    def __init__(self, world: World, appearance: Appearance = Appearance()) -> None:
        self.world = world
        self.appearance = appearance
        self._shader = _Shader(world, appearance)
        self._dirs: dict[PinholeCamera, np.ndarray] = {}

    def nadir(
        self, gsd_m: float, lighting: Lighting = Lighting(), *,
        extent: tuple[float, float, float, float] | None = None, rng: np.random.Generator | None = None,
    ) -> NadirRender:
        """Orthographic nadir view of ``extent`` (default: the whole world) at ``gsd_m`` m/px."""
        world = self.world
        if not gsd_m > 0:
            raise RenderError(f"gsd_m must be > 0, got {gsd_m}")
        xmin, xmax, ymin, ymax = extent if extent is not None else world.extent
        W = int(round((xmax - xmin) / gsd_m))
        H = int(round((ymax - ymin) / gsd_m))
        if W < 1 or H < 1:
            raise RenderError(f"extent {extent} is smaller than one {gsd_m} m pixel")
        xs = xmin + (np.arange(W) + 0.5) * gsd_m
        ys = ymax - (np.arange(H) + 0.5) * gsd_m
        gx, gy = np.meshgrid(xs, ys)
        top = float(world.terrain.z_m.max() + world.rocks.height_m.max(initial=0.0) + 10.0)
        rays = np.zeros((H * W, 6), dtype=np.float32)
        rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = gx.ravel(), gy.ravel(), top, -1.0
        hit, rock, _, p, normal = _hits(world, rays)
        sun = lighting.sun_dir()
        lit = _sunlit(world, p, normal, sun, hit & (normal @ sun > 0))
        grey = _grey(self._shader, lighting, hit, rock, p, normal, lit)
        image = _to_uint8(grey.reshape(H, W), self.appearance, rng)
        return NadirRender(image, rock.reshape(H, W).astype(np.int32),
                           (xmin, xmin + W * gsd_m, ymax - H * gsd_m, ymax), gsd_m)

    def pinhole(
        self, T_world_cam: np.ndarray, camera: "PinholeCamera", lighting: Lighting = Lighting(),
        *, rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pinhole view at ``T_world_cam`` (4, 4, optical frame): image (H, W) uint8,
        instance (H, W) int32 rock rows (-1: none), optical depth (H, W) metres (inf: sky)."""
        T = np.asarray(T_world_cam, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RenderError(f"T_world_cam must be a finite 4x4 pose, got shape {T.shape}")
        if camera not in self._dirs:
            self._dirs[camera] = camera.ray_dirs_cam().astype(np.float32)
        d_cam = self._dirs[camera]
        R = T[:3, :3].astype(np.float32)
        rays = np.empty((len(d_cam), 6), dtype=np.float32)
        rays[:, :3], rays[:, 3:] = T[:3, 3], d_cam @ R.T
        hit, rock, t_hit, p, normal = _hits(self.world, rays)
        sun = lighting.sun_dir().astype(np.float32)
        lit = _sunlit(self.world, p, normal, sun, hit & (normal @ sun > 0))
        grey = _grey(self._shader, lighting, hit, rock, p, normal, lit)
        H, W = camera.height_px, camera.width_px
        image = _to_uint8(grey.reshape(H, W), self.appearance, rng)
        return image, rock.reshape(H, W).astype(np.int32), (t_hit * d_cam[:, 2]).reshape(H, W)

    def stereo(
        self, T_world_left: np.ndarray, camera: "PinholeCamera", baseline_m: float,
        lighting: Lighting = Lighting(), *, rng: np.random.Generator | None = None,
    ) -> "StereoRender":
        """Render the left camera at ``T_world_left`` (4, 4, optical frame) and the right one
        ``baseline_m`` along the left camera's +x. Both views share one primary ray cast; the
        right view reuses the left view's shadow test where it sees the same surface point."""
        world = self.world
        T = np.asarray(T_world_left, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RenderError(f"T_world_left must be a finite 4x4 pose, got shape {T.shape}")
        if not baseline_m > 0:
            raise RenderError(f"baseline_m must be > 0, got {baseline_m}")
        if camera not in self._dirs:
            self._dirs[camera] = camera.ray_dirs_cam().astype(np.float32)
        d_cam = self._dirs[camera]
        R = T[:3, :3].astype(np.float32)
        d_w = d_cam @ R.T
        o_left = T[:3, 3].astype(np.float32)
        n = len(d_w)
        rays = np.empty((2 * n, 6), dtype=np.float32)
        rays[:n, :3], rays[n:, :3] = o_left, o_left + np.float32(baseline_m) * R[:, 0]
        rays[:n, 3:], rays[n:, 3:] = d_w, d_w
        hit, rock, t_hit, p, normal = _hits(world, rays)
        sun = lighting.sun_dir().astype(np.float32)
        facing = hit & (normal @ sun > 0)
        H, W = camera.height_px, camera.width_px
        lit = np.zeros(2 * n, dtype=bool)
        lit[:n] = _sunlit(world, p[:n], normal[:n], sun, facing[:n])
        depth = (t_hit[:n] * d_cam[:, 2]).reshape(H, W)
        # right-view points also seen by the left view take the left view's shadow flag
        q = (p[n:] - o_left) @ R
        z = np.where(facing[n:], q[:, 2], np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.floor(camera.f_px * q[:, 0] / z + camera.cx_px)
            v = np.floor(camera.f_px * q[:, 1] / z + camera.cy_px)
        inside = facing[n:] & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ui, vi = u[inside].astype(int), v[inside].astype(int)
        same = np.abs(depth[vi, ui] - z[inside]) < 0.01 + 0.01 * z[inside]
        reuse = np.flatnonzero(inside)[same]
        lit[n + reuse] = lit[:n].reshape(H, W)[vi[same], ui[same]]
        todo = facing[n:].copy()
        todo[reuse] = False
        lit[n:] |= _sunlit(world, p[n:], normal[n:], sun, todo)
        grey = _grey(self._shader, lighting, hit, rock, p, normal, lit)
        rng = rng if rng is not None else np.random.default_rng([self.appearance.seed, 13])
        left = _to_uint8(grey[:n].reshape(H, W), self.appearance, rng)
        right = _to_uint8(grey[n:].reshape(H, W), self.appearance, rng)
        return StereoRender(left, right, rock[:n].reshape(H, W).astype(np.int32),
                            rock[n:].reshape(H, W).astype(np.int32), depth, T, camera, float(baseline_m))


def render_nadir(
    world: World, gsd_m: float, lighting: Lighting = Lighting(), appearance: Appearance = Appearance(),
    *, extent: tuple[float, float, float, float] | None = None, rng: np.random.Generator | None = None,
) -> NadirRender:
    """One-off :meth:`Renderer.nadir` of ``world`` (see there)."""
    return Renderer(world, appearance).nadir(gsd_m, lighting, extent=extent, rng=rng)


@dataclass(frozen=True)
class PinholeCamera:
    """Rectified pinhole camera: image size, focal length and principal point in pixels."""

    width_px: int
    height_px: int
    f_px: float
    cx_px: float
    cy_px: float

    @staticmethod
    def from_fov(width_px: int, height_px: int, hfov_deg: float) -> "PinholeCamera":
        """Camera with horizontal field of view ``hfov_deg`` and a centred principal point."""
        if width_px < 1 or height_px < 1 or not 0 < hfov_deg < 170:
            raise RenderError(f"bad camera: {width_px} x {height_px} px, hfov {hfov_deg} deg")
        f = 0.5 * width_px / np.tan(np.deg2rad(hfov_deg) / 2)
        return PinholeCamera(int(width_px), int(height_px), float(f), width_px / 2.0, height_px / 2.0)

    def ray_dirs_cam(self) -> np.ndarray:
        """Unit ray directions (H*W, 3) through the pixel centres, optical frame, row-major."""
        u = np.arange(self.width_px) + 0.5
        v = np.arange(self.height_px) + 0.5
        gu, gv = np.meshgrid(u, v)
        d = np.stack([(gu - self.cx_px) / self.f_px, (gv - self.cy_px) / self.f_px, np.ones_like(gu)], axis=-1)
        d = d.reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, xyz_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) (u, v) of optical-frame points ``xyz_cam`` (N, 3) (z > 0)."""
        p = np.reshape(xyz_cam, (-1, 3))
        return np.column_stack([self.f_px * p[:, 0] / p[:, 2] + self.cx_px, self.f_px * p[:, 1] / p[:, 2] + self.cy_px])


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


def render_stereo(
    world: World, T_world_left: np.ndarray, camera: PinholeCamera, baseline_m: float,
    lighting: Lighting = Lighting(), appearance: Appearance = Appearance(),
    *, rng: np.random.Generator | None = None,
) -> StereoRender:
    """One-off :meth:`Renderer.stereo` of ``world`` (see there)."""
    return Renderer(world, appearance).stereo(T_world_left, camera, baseline_m, lighting, rng=rng)

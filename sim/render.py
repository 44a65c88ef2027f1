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

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

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


_REMAP_COLS = 1024  # cv2.remap wants maps under 32767 px a side: long point lists are folded


def _bilinear(grid: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) float32 of ``grid`` (h, w) float32 at continuous indices (column
    ``fx``, row ``fy``) (N,), edge values outside (as ``map_coordinates(order=1, mode="nearest")``)."""
    n = len(fx)
    rows = max(-(-n // _REMAP_COLS), 1)
    mx = np.zeros(rows * _REMAP_COLS, np.float32)
    my = np.zeros(rows * _REMAP_COLS, np.float32)
    mx[:n], my[:n] = fx, fy
    out = cv2.remap(grid, mx.reshape(rows, _REMAP_COLS), my.reshape(rows, _REMAP_COLS), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n]


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
        self._tex = (grid / (grid.std() + 1e-12)).astype(np.float32)
        self._origin = np.array([xmin - cell, ymin - cell], np.float32)
        self._cell = np.float32(cell)
        n = len(world.rocks)
        self._rock_albedo = (app.rock_albedo * np.exp(app.rock_albedo_spread * rng.standard_normal(n))).astype(np.float32)
        self.app = app

    def albedo(self, xyz: np.ndarray, rock: np.ndarray) -> np.ndarray:
        """Albedo (N,) float32 of surface points ``xyz`` (N, 3) owned by ``rock`` (N,) (-1: soil)."""
        fx = (xyz[:, 0] - self._origin[0]) / self._cell
        fy = (xyz[:, 1] - self._origin[1]) / self._cell
        tex = _bilinear(self._tex, fx, fy)
        amp = np.float32(self.app.texture_amplitude)
        out = np.float32(self.app.soil_albedo) * (1.0 + amp * tex)
        on_rock = np.flatnonzero(rock >= 0)
        if len(on_rock):
            out[on_rock] = self._rock_albedo[rock[on_rock]] * (1.0 + np.float32(0.3) * amp * tex[on_rock])
        return out


class _Caster:
    """First-hit and shadow queries on a world's ray-casting scene, float32 throughout, returning
    the hit rays only (sky rays cost nothing after the cast)."""

    def __init__(self, world: World) -> None:
        from sim.open3d_loader import open3d

        rs = world.raycast_scene()
        self._core = open3d().core
        self._scene = rs.scene
        self._rock_geometry = rs.rock_geometry
        self._triangle_rock = np.asarray(world.rocks.triangle_rock, dtype=np.int32)
        z_top = float(world.terrain.z_m.max())
        if len(world.rocks):
            z_top = max(z_top, float(world.rocks.vertices_m[:, 2].max()))
        self.z_top = z_top
        self.z_bottom = float(world.terrain.z_m.min())

    def first_hits(self, rays: np.ndarray):
        """Cast ``rays`` (N, 6) float32; for the K rays that hit: their indices (K,), distance
        (K,), rock row (K,) (-1: terrain), hit point (K, 3) and unit normal (K, 3) turned towards
        the ray's origin."""
        rays = np.ascontiguousarray(rays, dtype=np.float32)
        ans = self._scene.cast_rays(self._core.Tensor.from_numpy(rays))
        t = ans["t_hit"].numpy()
        idx = np.flatnonzero(np.isfinite(t))
        t = t[idx]
        geom = ans["geometry_ids"].numpy()[idx]
        prim = ans["primitive_ids"].numpy()[idx]
        rock = np.full(len(idx), -1, dtype=np.int32)
        on_rock = np.flatnonzero(geom == self._rock_geometry)
        rock[on_rock] = self._triangle_rock[prim[on_rock]]
        normal = np.take(ans["primitive_normals"].numpy(), idx, axis=0)  # take: a fast row gather
        hit_rays = np.take(rays, idx, axis=0)
        back = np.flatnonzero(_dot(normal, hit_rays[:, 3:6]) > -1e-12)  # rare: meshes wound inwards
        normal[back] = -normal[back]
        p = np.empty((len(idx), 3), dtype=np.float32)
        for c in range(3):  # column by column: broadcasting over the strided (K, 6) rows is slower
            np.multiply(hit_rays[:, 3 + c], t, out=p[:, c])
            p[:, c] += hit_rays[:, c]
        return idx, t, rock, p, normal

    def sunlit(self, p: np.ndarray, normal: np.ndarray, sun: np.ndarray) -> np.ndarray:
        """Boolean (N,): surface points ``p`` (N, 3) (offset 1 cm along ``normal``) whose ray
        towards the unit ``sun`` (3,) leaves the scene unblocked."""
        if len(p) == 0:
            return np.zeros(0, dtype=bool)
        rays = np.empty((len(p), 6), dtype=np.float32)
        for c in range(3):
            np.multiply(normal[:, c], np.float32(0.01), out=rays[:, c])
            rays[:, c] += p[:, c]
            rays[:, 3 + c] = sun[c]
        # above the highest vertex nothing can block the sun: stop the ray there
        t_far = (self.z_top - self.z_bottom + 0.1) / max(float(sun[2]), 1e-3)
        blocked = self._scene.test_occlusions(self._core.Tensor.from_numpy(rays), tfar=t_far).numpy()
        return ~blocked


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products (N,) of (N, 3) arrays (column arithmetic, faster than einsum here)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _toward(normal: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Cosines (N,) between unit normals (N, 3) and the unit ``sun`` (3,)."""
    return normal[:, 0] * sun[0] + normal[:, 1] * sun[1] + normal[:, 2] * sun[2]


def _light(lighting: Lighting, sun: np.ndarray, cos_sun: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """Light (N,) float32 on surface points whose normal makes ``cos_sun`` (N,) with the sun:
    ambient + direct sun (Lambert) where ``lit``."""
    lambert = np.clip(cos_sun, 0.0, 1.0)
    direct = np.float32((1.0 - lighting.ambient) / max(float(sun[2]), 0.5))
    return np.float32(lighting.ambient) + direct * lambert * lit


def _grey(shader: _Shader, n_rays: int, idx: np.ndarray, rock: np.ndarray, p: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Grey level (n_rays,) float32 in [0, 1]: albedo x light at the hit rays ``idx``, the sky level elsewhere."""
    grey = np.full(n_rays, shader.app.sky_level, dtype=np.float32)
    grey[idx] = np.clip(shader.albedo(p, rock) * light, 0.0, 1.0)
    return grey


def _to_uint8(grey: np.ndarray, app: Appearance, rng: np.random.Generator | None) -> np.ndarray:
    img = np.float32(255.0) * grey.astype(np.float32)
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
    """Renders one world under one appearance (texture, rock albedos and the ray caster are built once)."""

    def __init__(self, world: World, appearance: Appearance = Appearance()) -> None:
        self.world = world
        self.appearance = appearance
        self._shader = _Shader(world, appearance)
        self._caster: _Caster | None = None
        self._dirs: dict = {}  # per camera: unit ray directions (and their optical z for a pair)

    @property
    def caster(self) -> _Caster:
        """The world's ray caster (built on first use)."""
        if self._caster is None:
            self._caster = _Caster(self.world)
        return self._caster

    def _shade(self, rays: np.ndarray, lighting: Lighting):
        """First hits of ``rays`` (N, 6), their shadow test and grey level (N,); returns
        (grey, hit indices, rock rows, distances)."""
        sun = lighting.sun_dir().astype(np.float32)
        idx, t, rock, p, normal = self.caster.first_hits(rays)
        lit = np.zeros(len(idx), dtype=bool)
        cos_sun = _toward(normal, sun)
        facing = np.flatnonzero(cos_sun > 0)
        lit[facing] = self.caster.sunlit(np.take(p, facing, axis=0), np.take(normal, facing, axis=0), sun)
        grey = _grey(self._shader, len(rays), idx, rock, p, _light(lighting, sun, cos_sun, lit))
        return grey, idx, rock, t

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
        xs = (xmin + (np.arange(W) + 0.5) * gsd_m).astype(np.float32)
        ys = (ymax - (np.arange(H) + 0.5) * gsd_m).astype(np.float32)
        rays = np.zeros((H, W, 6), dtype=np.float32)
        rays[:, :, 0], rays[:, :, 1] = xs[None, :], ys[:, None]
        rays[:, :, 2], rays[:, :, 5] = self.caster.z_top + 10.0, -1.0
        grey, idx, rock, _ = self._shade(rays.reshape(-1, 6), lighting)
        instance = np.full(H * W, -1, dtype=np.int32)
        instance[idx] = rock
        image = _to_uint8(grey.reshape(H, W), self.appearance, rng)
        return NadirRender(image, instance.reshape(H, W), (xmin, xmin + W * gsd_m, ymax - H * gsd_m, ymax), gsd_m)

    def _camera_rays(self, T: np.ndarray, camera: PinholeCamera, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (H*W, 3) of ``camera`` in the optical frame and in the world at ``T``."""
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RenderError(f"{what} must be a finite 4x4 pose, got shape {T.shape}")
        if camera not in self._dirs:
            self._dirs[camera] = camera.ray_dirs_cam().astype(np.float32)
        d_cam = self._dirs[camera]
        return d_cam, d_cam @ T[:3, :3].astype(np.float32).T

    def _z_two_views(self, camera: PinholeCamera, d_cam: np.ndarray) -> np.ndarray:
        """Optical z (2 H W,) of the unit ray directions of ``camera``, left view then right view."""
        key = ("z2", camera)
        if key not in self._dirs:
            self._dirs[key] = np.concatenate([d_cam[:, 2], d_cam[:, 2]])
        return self._dirs[key]

    def pinhole(
        self, T_world_cam: np.ndarray, camera: PinholeCamera, lighting: Lighting = Lighting(),
        *, rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pinhole view at ``T_world_cam`` (4, 4, optical frame): image (H, W) uint8,
        instance (H, W) int32 rock rows (-1: none), optical depth (H, W) metres (inf: sky)."""
        T = np.asarray(T_world_cam, dtype=float)
        d_cam, d_w = self._camera_rays(T, camera, "T_world_cam")
        rays = np.empty((len(d_cam), 6), dtype=np.float32)
        rays[:, :3], rays[:, 3:] = T[:3, 3], d_w
        grey, idx, rock, t = self._shade(rays, lighting)
        H, W = camera.height_px, camera.width_px
        instance = np.full(H * W, -1, dtype=np.int32)
        instance[idx] = rock
        depth = np.full(H * W, np.inf, dtype=np.float32)
        depth[idx] = t * d_cam[idx, 2]
        image = _to_uint8(grey.reshape(H, W), self.appearance, rng)
        return image, instance.reshape(H, W), depth.reshape(H, W)

    def stereo(
        self, T_world_left: np.ndarray, camera: PinholeCamera, baseline_m: float,
        lighting: Lighting = Lighting(), *, rng: np.random.Generator | None = None,
    ) -> StereoRender:
        """Render the left camera at ``T_world_left`` (4, 4, optical frame) and the right one
        ``baseline_m`` along the left camera's +x. Both views share one primary ray cast; shadow
        rays are cast for sun-facing hits only, and the right view reuses the left view's shadow
        test wherever it sees the same surface point."""
        T = np.asarray(T_world_left, dtype=float)
        d_cam, d_w = self._camera_rays(T, camera, "T_world_left")
        if not baseline_m > 0:
            raise RenderError(f"baseline_m must be > 0, got {baseline_m}")
        R = T[:3, :3].astype(np.float32)
        o_left = T[:3, 3].astype(np.float32)
        n = len(d_w)
        H, W = camera.height_px, camera.width_px
        rays = np.empty((2 * n, 6), dtype=np.float32)
        rays[:n, :3], rays[n:, :3] = o_left, o_left + np.float32(baseline_m) * R[:, 0]
        rays[:n, 3:], rays[n:, 3:] = d_w, d_w
        idx, t, rock, p, normal = self.caster.first_hits(rays)
        sun = lighting.sun_dir().astype(np.float32)
        cos_sun = _toward(normal, sun)
        facing = cos_sun > 0
        n_left = int(np.searchsorted(idx, n))  # hits are sorted: left view first
        z_hit = t * self._z_two_views(camera, d_cam)[idx]  # optical depth of every hit (same axis in both views)
        depth = np.full(n, np.inf, dtype=np.float32)
        depth[idx[:n_left]] = z_hit[:n_left]
        lit = np.zeros(len(idx), dtype=bool)
        fl = np.flatnonzero(facing[:n_left])
        lit[fl] = self.caster.sunlit(np.take(p, fl, axis=0), np.take(normal, fl, axis=0), sun)
        lit_left = np.zeros(n, dtype=bool)
        lit_left[idx[fl]] = lit[fl]
        # a right-view point at pixel (row, col) and depth z lies in the left view at row, column
        # col + 0.5 + f b / z (rectified pair); where the left view sees the same surface there
        # and the shadow flag does not change across that pixel's row neighbours (the point lies
        # within half a pixel of the left hit), it takes the left view's flag
        lit_img = lit_left.reshape(H, W)
        steady = np.ones((H, W), dtype=bool)
        steady[:, 1:] = lit_img[:, 1:] == lit_img[:, :-1]
        steady[:, :-1] &= steady[:, 1:].copy()
        steady = steady.ravel()
        fr = n_left + np.flatnonzero(facing[n_left:])
        pix = idx[fr] - n
        row = pix // W
        col = pix - row * W
        z = z_hit[fr]
        u = np.floor(col + np.float32(0.5) + np.float32(camera.f_px * baseline_m) / z).astype(np.intp)
        inside = np.flatnonzero(u < W)
        left_pix = row[inside] * W + u[inside]
        same = (np.abs(depth[left_pix] - z[inside]) < 0.01 + 0.01 * z[inside]) & steady[left_pix]
        reuse = inside[same]
        lit[fr[reuse]] = lit_left[left_pix[same]]
        rest = np.ones(len(fr), dtype=bool)
        rest[reuse] = False
        todo = fr[rest]
        lit[todo] = self.caster.sunlit(np.take(p, todo, axis=0), np.take(normal, todo, axis=0), sun)
        grey = _grey(self._shader, 2 * n, idx, rock, p, _light(lighting, sun, cos_sun, lit))
        instance = np.full(2 * n, -1, dtype=np.int32)
        instance[idx] = rock
        rng = rng if rng is not None else np.random.default_rng([self.appearance.seed, 13])
        left = _to_uint8(grey[:n].reshape(H, W), self.appearance, rng)
        right = _to_uint8(grey[n:].reshape(H, W), self.appearance, rng)
        return StereoRender(left, right, instance[:n].reshape(H, W), instance[n:].reshape(H, W), depth.reshape(H, W), T, camera,
                            float(baseline_m))


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
    def from_fov(width_px: int, height_px: int, hfov_deg: float) -> PinholeCamera:
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

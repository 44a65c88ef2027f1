"""The renderer of one world under one appearance: texture, rock albedos and the world's ray
caster are built once and reused by every view."""

from __future__ import annotations

import numpy as np

from sim.render.camera import PinholeCamera
from sim.render.config import Appearance, Lighting, RenderError
from sim.render.nadir import NadirRender, render_nadir_view
from sim.render.shading import Shader
from sim.render.stereo import StereoRender, render_pinhole, render_stereo_pair
from sim.world import RaycastScene, World


class Renderer:
    """Renders ``world`` under ``appearance``; ``nthreads`` caps the ray-casting threads (0: all
    cores; 1 gives the one-core cost, as ``fgslam bench detect`` measures it)."""

    def __init__(self, world: World, appearance: Appearance = Appearance(), nthreads: int = 0) -> None:
        if nthreads < 0:
            raise RenderError(f"nthreads must be >= 0 (0: all cores), got {nthreads}")
        self.world = world
        self.appearance = appearance
        self.nthreads = int(nthreads)
        self._shader = Shader(world, appearance)

    @property
    def scene(self) -> RaycastScene:
        """The world's ray-casting scene (built on first use, cached by the world)."""
        return self.world.raycast_scene()

    def nadir(
        self, gsd_m: float, lighting: Lighting = Lighting(), *,
        extent: tuple[float, float, float, float] | None = None, rng: np.random.Generator | None = None,
    ) -> NadirRender:
        """Orthographic nadir view of ``extent`` (default: the whole world) at ``gsd_m`` m/px."""
        return render_nadir_view(self.scene, self._shader, gsd_m, lighting,
                                 extent if extent is not None else self.world.extent, rng, self.nthreads)

    def pinhole(
        self, T_world_cam: np.ndarray, camera: PinholeCamera, lighting: Lighting = Lighting(),
        *, rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pinhole view at ``T_world_cam`` (4, 4, optical frame): image (H, W) uint8,
        instance (H, W) int32 rock rows (-1: none), optical depth (H, W) metres (inf: sky)."""
        return render_pinhole(self.scene, self._shader, T_world_cam, camera, lighting, rng, self.nthreads)

    def stereo(
        self, T_world_left: np.ndarray, camera: PinholeCamera, baseline_m: float,
        lighting: Lighting = Lighting(), *, rng: np.random.Generator | None = None,
    ) -> StereoRender:
        """Render the left camera at ``T_world_left`` (4, 4, optical frame) and the right one
        ``baseline_m`` along the left camera's +x, from one primary ray cast (shadow rays: see
        :mod:`sim.render.shadows`)."""
        return render_stereo_pair(self.scene, self._shader, T_world_left, camera, baseline_m, lighting, rng,
                                  self.nthreads)


def render_nadir(
    world: World, gsd_m: float, lighting: Lighting = Lighting(), appearance: Appearance = Appearance(),
    *, extent: tuple[float, float, float, float] | None = None, rng: np.random.Generator | None = None,
) -> NadirRender:
    """One-off :meth:`Renderer.nadir` of ``world`` (see there)."""
    return Renderer(world, appearance).nadir(gsd_m, lighting, extent=extent, rng=rng)


def render_stereo(
    world: World, T_world_left: np.ndarray, camera: PinholeCamera, baseline_m: float,
    lighting: Lighting = Lighting(), appearance: Appearance = Appearance(),
    *, rng: np.random.Generator | None = None,
) -> StereoRender:
    """One-off :meth:`Renderer.stereo` of ``world`` (see there)."""
    return Renderer(world, appearance).stereo(T_world_left, camera, baseline_m, lighting, rng=rng)

"""Image renderer: a nadir orthographic "orbital" view and the rover's rectified stereo pair.

Both views ray-cast the world's terrain and rock meshes with open3d's ``RaycastingScene`` (CPU,
through :class:`sim.world.RaycastScene`), shade the hit points with a Lambertian sun plus ambient
light, darken points whose ray towards the sun is blocked (cast shadows, the cue nadir rock
counting relies on), and return an exact per-pixel rock instance id (the row in
``world.rocks``, -1 for terrain or sky) from which box labels are made. Soil albedo carries a
seeded value-noise texture and each rock its own albedo, so that a detector has to learn shape
and shadow rather than a single rock colour.

Modules: ``config`` (Lighting, Appearance, RenderError), ``camera`` (PinholeCamera, pixel rays),
``shading`` (texture, albedo, light, sensor), ``shadows`` (which shadow rays are cast),
``nadir`` and ``stereo`` (the views), ``renderer`` (:class:`Renderer`, the composer).
"""

from sim.render.camera import PinholeCamera
from sim.render.config import Appearance, Lighting, RenderError
from sim.render.nadir import NadirRender
from sim.render.renderer import Renderer, render_nadir, render_stereo
from sim.render.stereo import StereoRender

__all__ = [
    "Appearance",
    "Lighting",
    "NadirRender",
    "PinholeCamera",
    "RenderError",
    "Renderer",
    "StereoRender",
    "render_nadir",
    "render_stereo",
]

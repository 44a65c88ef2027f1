"""Render settings: the sun (:class:`Lighting`), albedos, texture and sensor noise
(:class:`Appearance`), and the error a bad request raises."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.errors import SimError


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

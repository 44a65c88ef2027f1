"""Height from an orbital terrain model: a fix's (x, y) read in the DEM gives base_link's z.

Planar fixes leave the height free; on kilometres it drifts with the pitch the odometry
integrates. A rover on the ground is where the terrain is, so the DEM at the fix's position,
plus base_link's height over the wheel-contact plane, is a measurement of z at ``t_meas``:

    z = DEM(x_fix, y_fix) + base_height cos(slope)

with variance ``sigma_m^2 + g' C_xy g`` (the model's vertical error and the terrain under the
wheels, and the fix's planar error through the slope ``g``) and covariance ``g' C_xy,yaw`` with
the fix's (x, y, yaw): the fix becomes (x, y, yaw, z), delivered, gated and replayed as the
planar one is. The DEM's error is correlated over ``correlation_m`` (a stereo DTM's error is
smooth), so a height is attached only to a fix at least that far from the previous fix with a
height: nearer heights would count the same error twice.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

from fgslam.errors import FgslamError
from fgslam.fix_sources import FixProducer, WrappedProducer
from fgslam.relocalizer import FixAttempt
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.config import NonNegative, Positive, checked
from reloc.dem import Dem
from reloc.measurements import FixHeight, GlobalFix


class TerrainHeightError(FgslamError):
    """The terrain-height settings are invalid."""


@dataclass(frozen=True)
@checked(TerrainHeightError)
class TerrainHeightConfig:
    """How fixes get a height from the DEM (used when the inputs have one)."""

    enabled: bool = True
    # vertical error of the DEM where the rover stands: the model's own (a HiRISE-class stereo DTM
    # at 1 m posts states 0.1-0.2 m) and the terrain under the wheels that 1 m posts smooth away
    sigma_m: Positive = 0.16
    correlation_m: NonNegative = 25.0  # the DEM error's correlation length: the least spacing of heights
    base_height_m: float = 0.15  # base_link above the wheel-contact plane, along its normal (rover geometry)
    max_slope: Positive = 0.6  # steeper cells (|grad|, 31 deg) give no height: a rover does not stand there


class DemHeights:
    """Attaches heights to fixes (module doc); counts what it did."""

    def __init__(self, dem: Dem, cfg: TerrainHeightConfig | None = None) -> None:
        self.dem = dem
        self.cfg = cfg or TerrainHeightConfig()
        self._last_xy: tuple[float, float] | None = None
        self.n_attached = 0
        self.n_too_close = 0
        self.n_no_data = 0
        self.n_too_steep = 0

    def attach(self, fix: GlobalFix) -> GlobalFix:
        """``fix`` with its height, or as it is (too close to the last height, no data, too steep)."""
        cfg = self.cfg
        if fix.height is not None:
            return fix
        if self._last_xy is not None and math.hypot(fix.x_m - self._last_xy[0], fix.y_m - self._last_xy[1]) < cfg.correlation_m:
            self.n_too_close += 1
            return fix
        s = self.dem.sample(fix.x_m, fix.y_m)
        if s is None:
            self.n_no_data += 1
            return fix
        g = s.grad
        slope2 = float(g @ g)
        if slope2 > cfg.max_slope**2:
            self.n_too_steep += 1
            return fix
        C = fix.cov_xyyaw
        cov_z = g @ C[:2, :]  # (3,): z's covariance with (x, y, yaw)
        var = cfg.sigma_m**2 + float(cov_z[:2] @ g)
        z = s.z_m + cfg.base_height_m / math.sqrt(1.0 + slope2)
        self._last_xy = (fix.x_m, fix.y_m)
        self.n_attached += 1
        return replace(fix, height=FixHeight(z, var, cov_z))

    def counts(self) -> dict:
        return {"attached": self.n_attached, "too_close": self.n_too_close, "no_data": self.n_no_data,
                "too_steep": self.n_too_steep}


class WithHeight(WrappedProducer):
    """A relocalizer whose fixes carry the DEM's height (one :class:`DemHeights` may serve several,
    so that the spacing holds across them)."""

    def __init__(self, inner: FixProducer, heights: DemHeights) -> None:
        super().__init__(inner)
        self.heights = heights

    def attempt(self, maps: Mapping[str, LandmarkMap], est: PoseEstimate) -> FixAttempt:
        att = self.inner.attempt(maps, est)
        if att.fix is None:
            return att
        return replace(att, fix=self.heights.attach(att.fix))


def with_heights(relocalizers: list[FixProducer], dem: Dem | None, cfg: TerrainHeightConfig) -> list[FixProducer]:
    """``relocalizers`` whose fixes carry heights from ``dem`` (as they are without a DEM or when
    ``cfg.enabled`` is off)."""
    if dem is None or not cfg.enabled or not relocalizers:
        return list(relocalizers)
    heights = DemHeights(dem, cfg)
    return [WithHeight(r, heights) for r in relocalizers]


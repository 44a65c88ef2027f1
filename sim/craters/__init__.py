"""Impact craters for the orbital-scale worlds: size-frequency model, seeded populations, morphology
stamped onto heightmaps, and ejecta blocks. Usable on its own (no world, no tiles needed).

API (stable)
------------
``CraterSFD(age_gyr=1.0, production="hartmann2005", equilibrium=True, d_min_m=1, d_max_m=200)``
    Hartmann (2005) Mars production function x age scale, capped by Hartmann's (1984)
    equilibrium (formulas and sources in :mod:`sim.craters.sfd`). ``cumulative_per_m2(D)``,
    ``bin_density_per_m2(D_lo)`` (root-2 bins), ``expected_count(area_m2, d_lo, d_hi)``,
    ``sample_diameters(n, rng)``, ``saturation_ratio(D)``.
``sample_craters(sfd, extent, rng) -> Craters``
    Seeded population of a box (xmin, xmax, ymin, ymax) in metres: Poisson count, diameters from
    the model, uniform centres, degradation from the saturation state.
``Craters(xy_m, diameter_m, degradation, id)``
    The crater table; ``depth_m`` (rim crest to floor) and ``rim_height_m`` follow from the
    morphology; ``subset``, ``concat``, ``reaching(extent, reach_radii)``.
``stamp_craters(heightmap, craters) -> Heightmap``; ``stamp_relief(z, extent, ...)``;
``crater_relief(xy, centres, diameters, degradation)``
    Heights in, heights out: a fresh crater is a bowl of depth 0.2 D with a rim 0.04 D high and an
    ejecta blanket to 3 R; degraded craters are filled and smoothed (shallower, rounded rims);
    overlapping craters add (:mod:`sim.craters.morphology`).
``ejecta_blocks(craters, seed, EjectaConfig()) -> EjectaBlocks``
    Blocks (xy, diameter, crater id) around fresh craters, seeded per crater
    (:mod:`sim.craters.ejecta`).

Example: a 100 m patch at 0.25 m with the craters of a 3 Gyr surface::

    rng = np.random.default_rng(0)
    hm = Heightmap(np.zeros((401, 401)), (0.0, 100.0, 0.0, 100.0))
    craters = sample_craters(CraterSFD(age_gyr=3.0), (-50.0, 150.0, -50.0, 150.0), rng)
    hm = stamp_craters(hm, craters.reaching(hm.extent, INFLUENCE_RADIUS))
"""

from __future__ import annotations

from sim.craters.ejecta import EjectaBlocks, EjectaConfig, blocky, ejecta_blocks, expected_blocks
from sim.craters.morphology import (
    FRESH_DEPTH_RATIO,
    FRESH_RIM_RATIO,
    INFLUENCE_RADIUS,
    crater_relief,
    depth_ratio,
    fresh_profile,
    profile,
    quantise,
    rim_ratio,
    stamp_relief,
)
from sim.craters.population import Craters, sample_craters, sample_degradation
from sim.craters.sfd import CraterSFD, hartmann_age_scale
from sim.terrain import Heightmap


def stamp_craters(heightmap: Heightmap, craters: Craters) -> Heightmap:
    """``heightmap`` with the relief of ``craters`` added (a new :class:`Heightmap`)."""
    z = stamp_relief(heightmap.z_m, heightmap.extent, craters.xy_m, craters.diameter_m, craters.degradation)
    return Heightmap(z, heightmap.extent)


__all__ = [
    "FRESH_DEPTH_RATIO",
    "FRESH_RIM_RATIO",
    "INFLUENCE_RADIUS",
    "CraterSFD",
    "Craters",
    "EjectaBlocks",
    "EjectaConfig",
    "blocky",
    "crater_relief",
    "depth_ratio",
    "ejecta_blocks",
    "expected_blocks",
    "fresh_profile",
    "hartmann_age_scale",
    "profile",
    "quantise",
    "rim_ratio",
    "sample_craters",
    "sample_degradation",
    "stamp_craters",
    "stamp_relief",
]

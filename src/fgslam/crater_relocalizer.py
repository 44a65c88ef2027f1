"""The crater kind's relocalizer: the constellation matcher on the crater map and the orbital
crater catalog, with crater-scale tolerances, turned into late (x, y, yaw) fixes.

It is the rock relocalizer (:class:`fgslam.relocalizer.Relocalizer`: local-map selection, search
prior, catalog crops, the rover-weighted final fit, correlated-fix deweighting) reading the
``craters`` map, with the defaults of :data:`CRATER_RELOCALIZER_DEFAULTS` under the user's
overrides (``CompareConfig.kind_relocalizers["craters"]``). What differs from rocks, and why:

- craters are metres across and tens of metres apart: the local constellation is taken within
  ``max_radius_m`` 80 m, the matcher's sigma (map vs catalog, per axis) is 0.3 m (the orbital
  centre error ~0.05 D plus half a pixel, the rover's rim fit 0.1-0.3 m), its inlier growth
  reaches 15 and 40 m and its density radius is 8 m;
- rim diameters are measured to ~10 % on both sides: diameter ratios beyond 1.5 are not paired;
- a few craters suffice where rocks need many: an attempt needs ``min_landmarks`` 6 mapped
  craters and a match 4 inliers (the matcher's false-alarm bound still decides);
- craters are seen seconds apart, so attempts come every 10 s;
- their triangles have sides of tens of metres, so the matcher's heading bins come from the local
  triangles' sides (``heading_arm_m`` None) rather than from rocks' 1.5 m;
- the estimate's own pose is verified first (``track``): a localized rover's map of 12 craters,
  6 of them catalogued, convinces as one guess where the triangle search, paying for its
  hypotheses, did not (cratered-3km's first 600 s: 35 -> 51 of 51 attempts with >= 6 catalogued
  craters mapped; docs/craters.md);
- where too few craters are mapped to match (young, sparse ground: sparse-5km's first 400 m
  passes 4-6 catalogued craters and no catalogued rock), one crater identified alone with its
  catalog entry fixes the rover's position (``single_landmark``; its gate and false-alarm bound
  in :class:`fgslam.relocalizer_config.RelocalizerConfig`), or two together; an identified
  crater's catalog centre is taken as good as 0.06 of its diameter per axis (``catalog_sigma_rel``:
  the orbital detector's centre error), not the matcher's 0.3 m, which a big crater's is not;
- such a fix can name its craters and entries (``anchor_landmarks``, off by default), so that a
  back-end puts each entry on its crater once rather than on the pose at every later fix: on
  sparse-5km's first 2.5 km that left the smoother 1.6-2.7 m off against 0.97 m with the pose
  fixes (docs/craters.md, "Catalog anchors, measured").

Beside the rock relocalizer a run gets fixes from rocks, from craters or from both, whichever the
place offers (each relocalizer labels its attempts with its kind).
"""

from __future__ import annotations

from fgslam.relocalizer import Relocalizer, RelocalizerConfig
from reloc.config import config_from_dict, config_to_dict
from reloc.measurements import RockCatalog

CRATER_MATCHER = {
    "sigma_m": 0.3, "min_inlier_radius_m": 0.3, "size_ratio_max": 1.5, "growth_reach_m": [15.0, 40.0],
    "density_radius_m": 8.0, "min_inliers": 4, "heading_arm_m": None,
}
CRATER_RELOCALIZER_DEFAULTS = RelocalizerConfig(
    period_s=10.0, min_landmarks=6, max_landmarks=80, max_radius_m=80.0, select="nearest", min_travel_m=1.0,
    fit_radius_m=40.0, sigma_floor_m=0.1, prior_min_radius_m=5.0, crop_margin_m=5.0, crop_snap_m=5.0,
    single_landmark=True, track=True, catalog_sigma_rel=0.06, matcher=CRATER_MATCHER,
)


def crater_relocalizer_config(overrides: RelocalizerConfig | dict | None = None) -> RelocalizerConfig:
    """The crater relocalizer's settings: :data:`CRATER_RELOCALIZER_DEFAULTS` under ``overrides``
    (a dict merges key by key, its ``matcher`` too; a :class:`RelocalizerConfig` is taken whole)."""
    if isinstance(overrides, RelocalizerConfig):
        return overrides
    data = dict(overrides or {})
    if "matcher" in data:
        data["matcher"] = {**CRATER_MATCHER, **dict(data["matcher"] or {})}
    base = config_to_dict(CRATER_RELOCALIZER_DEFAULTS)
    return config_from_dict(RelocalizerConfig, {**base, **data}, where="craters relocalizer.")


class CraterRelocalizer(Relocalizer):
    """The relocalizer of the ``craters`` kind (see module doc)."""

    def __init__(self, catalog: RockCatalog, config: RelocalizerConfig | dict | None = None, matcher=None) -> None:
        super().__init__(catalog, crater_relocalizer_config(config), matcher=matcher, kind="craters")

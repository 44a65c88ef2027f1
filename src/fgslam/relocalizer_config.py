"""Configuration of the rock relocalizer (:class:`fgslam.relocalizer.Relocalizer`): when and how
the local map is matched, and how a match becomes a fix. Defaults in code; the measurements
behind them are in docs/app.md."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from fgslam.errors import FgslamError
from reloc.config import Ge, Interval, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from reloc.errors import ConfigError


class RelocalizerError(FgslamError):
    """Bad relocalizer configuration or input."""


@dataclass(frozen=True)
@checked(RelocalizerError)
class RelocalizerConfig:
    """When and how the local map is matched, and how a match becomes a fix (defaults in code)."""

    # one attempt per period of stream time (goal: fixes >= 0.2 Hz; cnes: 0.147 Hz at 3 s, 0.219 at 2 s)
    period_s: Positive = 2.0
    min_obs: PositiveInt = 2  # landmarks seen fewer times are not matched (likely false positives)
    min_landmarks: Annotated[int, Ge(3)] = 8  # skip the attempt below this many usable landmarks
    # landmarks smaller than this fraction of the catalog's smallest entries (its 1st percentile
    # of sizes) cannot be in it and are left out of the local map (the rover's and the catalog's
    # size errors are 15-20 %): at HiRISE scale the catalog holds rocks of ~0.75 m and more, and
    # the small rocks only fed the search (plains-2km, first 3000 s: 112 rock attempts, all "no
    # match", 57.7 s of the 62.9 s of matching); 0: every landmark
    min_size_fraction: NonNegative = 0.7
    max_landmarks: Annotated[int, Ge(3)] = 160  # this many landmarks form the local constellation ...
    max_radius_m: Positive = 30.0  # ... chosen within this distance of the rover ...
    # ... "largest" first (the orbital catalog holds mostly the larger rocks: on a dense yard the
    # nearest 80 are small rocks in a few metres, few of them catalogued) or "nearest" first
    select: Literal["largest", "nearest"] = "largest"
    # Sparse ground: with fewer than sparse_below usable landmarks within max_radius_m, the radius
    # grows to sparse_radius_m (on a traverse that does not come back: the last ~80 m of path),
    # so the constellation holds enough catalogued rocks to match
    sparse_below: NonNegativeInt = 40
    sparse_radius_m: Positive = 80.0
    # The local map also holds the landmarks the back-end dropped (EKF marginalisation, fixed-lag
    # retirement) while last seen within window_path_m of estimated path, at most window_max_kept
    # (fgslam.local_window); window_path_m 0: the back-end's map only
    window_path_m: NonNegative = 150.0
    window_max_kept: PositiveInt = 2000
    # an attempt is skipped while the rover has moved less than min_travel_m and turned less than
    # min_turn_deg since the last one (standing still, its map and pose say nothing new: my2021,
    # 687 -> 554 attempts, the same ATE, 44 -> 48x real time); both 0: never skipped
    min_travel_m: NonNegative = 0.05
    # an attempt needs this many landmark observations added to the map since the previous attempt:
    # a map the rover has not seen lately (camera blackout) places the rover by odometry only, so
    # its match would be a confident fix of a dead-reckoned pose (docs/sim.md, "Faults"); 0: off
    min_new_observations: NonNegativeInt = 3
    # Backoff: after backoff_after consecutive attempts that matched nothing ("no match", "bad
    # scale": the attempts that cost a search), each further one doubles the period, up to
    # backoff_max_period_s; a fix resets it. A catalog that cannot hold this kind's map here costs
    # a search every period for nothing (rocks at HiRISE scale, rocky-1km: 0 fixes in 757
    # attempts, ~0.5 s each; docs/app.md "Attempt backoff"); 0: off
    backoff_after: NonNegativeInt = 10
    backoff_max_period_s: Positive = 30.0
    min_turn_deg: NonNegative = 3.0
    latency: Literal["fixed", "measured"] = "fixed"  # "fixed": t_recv = t_meas + delay_s; "measured": + matching wall time
    delay_s: NonNegative = 2.0
    latency_scale: Positive = 1.0  # multiplies the measured matching time (slower onboard CPU)
    sigma_floor_m: NonNegative = 0.05  # per-point residual sigma never below this
    sigma_yaw_floor_rad: NonNegative = 0.003
    inflation: Annotated[float, Ge(1)] = 1.75  # multiplies the residual sigma (unmodelled map distortion)
    map_cov_weight: NonNegative = 0.0  # weight of the landmarks' own planar covariance in sigma^2
    # A fix moves the rover with its map, so it is only as good as the rover's place relative to
    # the matched landmarks. A landmark placed from the rover's poses shares their drift; what the
    # rover has gained in uncertainty since the landmark was last seen (a camera blackout, a
    # stretch without rocks, metres of path) is its uncertainty relative to the rover, which no
    # match on it removes (fgslam.match_to_fix.rover_relative_cov_xy). Landmarks whose relative
    # sigma exceeds this many matcher sigmas are not matched (the map's old part would otherwise
    # outvote the part seen since and repeat the drifted pose: my2020 seed 1, a 120 s blackout,
    # EKF + reloc: 14 fixes 0.56-0.60 m off claiming 0.16-0.28 m); the inliers' relative
    # covariance, weighted as in the fit, is added to the fix's. None: every landmark, nothing
    # added. Not applied while lost (the whole map is then relative to an unknown start).
    max_relative_sigmas: Positive | None = 2.0
    # The fix describes the rover, so the final fit weighs each matched rock by how well the map
    # ties it to the rover: w = 1 / (1 + (d / fit_radius_m)^2) at distance d from the rover (a
    # relative map error that grows with distance and equals the catalog's at fit_radius_m),
    # covariance from the weighted fit. None: every inlier alike (the matcher's own fit). Seed 0,
    # iSAM2 + reloc, None -> 10: my2020 0.040 -> 0.034 m, my2021 0.034 -> 0.030, my2022 0.036 ->
    # 0.032, cnes 0.060 -> 0.057; my2020 seed 2 0.166 m / 62 % inside 3 sigma -> 0.060 m / 96 %
    # (a map bent on a climb gave fixes biased with it); docs/app.md
    fit_radius_m: Positive | None = 10.0
    max_scale_error: Annotated[float, Interval(gt=0, lt=1)] = 0.05  # reject matches whose scale is further than this from 1
    # Search prior: the map's centroid must land within prior_min_radius_m + prior_sigmas *
    # sigma_pos (largest std of the estimate's x/y) of where the estimate puts it; None: no prior.
    # Successive fixes share most inlier rocks, hence most of their catalog error: fusing them as
    # independent would make a back-end overconfident. correlation "rocks" (default): each fix's
    # covariance is multiplied by 1 + the mean, over its inlier catalog rocks, of how many earlier
    # fixes used that rock (sum over earlier fixes of the fraction of rocks shared with them; for
    # fixes on the same rocks the covariance-intersection bound, whenever they were made).
    # "window": 1 + number of fixes produced in the preceding correlation_window_s. "distance":
    # the fixes' errors as a Gauss-Markov process along the path, correlation exp(-d / L) between
    # fixes d metres of path apart, L = correlation_length_m: (1 + rho) / (1 - rho) with rho at the
    # path since the previous fix (reloc.covariance.distance_correlation_scale). "none": 1.
    correlation: Literal["rocks", "window", "distance", "none"] = "rocks"
    correlation_window_s: Positive = 60.0
    correlation_length_m: Positive = 15.0
    prior_sigmas: Positive | None = 6.0
    prior_min_radius_m: NonNegative = 3.0
    # an estimate whose largest planar sigma exceeds this is lost: its map is matched against the
    # whole catalog, with no prior (the back-end re-anchors on the fix, fgslam.backends.reanchor)
    lost_sigma_m: Positive = 5.0
    # Tracking: with a prior, first verify the pose the estimate gives (the map as it is, in the
    # estimate's world frame) and search only if that does not convince (reloc.matcher module doc).
    # Off by default: it saves matching time on dense catalogs (my2020 reference pass: matching
    # 17.1 -> 9.6 s CPU on the same snapshots) but a fix found from the estimate leans towards it
    # (my2022, iSAM2 + reloc: fixes' median error 0.023 -> 0.031 m, ATE 0.036 -> 0.042 m; my2020,
    # my2021, cnes: the same ATE within 2 %)
    track: bool = False
    # With a prior, match against the catalog rocks that can hold the map (within prior radius +
    # the map's extent + crop_margin_m of where the estimate puts it): a small index built per
    # attempt (a few ms) instead of hypotheses over the whole catalog. False: whole catalog.
    crop_catalog: bool = True
    crop_margin_m: NonNegative = 2.0
    # Crops are cut on a grid: centre snapped to crop_snap_m, radius rounded up to a multiple of
    # it (plus the snapping error), so successive attempts a few decimetres apart share one crop
    # and its index, kept in a cache of crop_cache crops. The crop still holds every rock that
    # can hold the map.
    crop_snap_m: Positive = 2.0
    crop_cache: PositiveInt = 8
    # Single landmark: where the local map holds too few landmarks to match (or they do not
    # match), one mapped landmark within single_radius_m of the rover may be identified with a
    # catalog entry on its own and fix the rover's position (not its heading). It is identified
    # when exactly one catalog entry of compatible size (ratio <= the matcher's size_ratio_max) lies
    # inside the gate (chi-square single_gate_chi2, 2 dof, of the landmark's world covariance S plus
    # the matcher's sigma_m per axis) and the odds that a chance entry lies that close rather than
    # the landmark's own (the catalog's local density of compatible sizes within
    # single_density_radius_m, the candidate counted, per m^2 of that disc inside the catalog's
    # bounding box, over the Gaussian density N(d; 0, S) at the
    # candidate's offset d) are at most single_max_false_alarm: the bound on a wrong fix per
    # attempt. On for every kind: where the catalog is dense the bound refuses (a kilometre
    # world's rocks: the same fixes on rocky-1km's first 400 m with it as without); where it is
    # sparse and the landmark well placed, one landmark does what a constellation cannot (ERC
    # MY2021's 23 catalogued rocks: too dense for it at 1e-3 with decimetre gates, docs/app.md)
    single_landmark: bool = True
    # Two landmarks: before one alone, two mapped landmarks are identified together
    # (fgslam.match_to_fix.identify_pair) with the single_* gate, radius, density and bound: each
    # in its own gate, and the pair of entries reproducing the landmarks' separation within the
    # gate of their relative error, which the rover's drift does not widen (a few decimetres where
    # the own gates hold the drift of a sparse yard). The fix has a heading (as good as the pair is
    # long). ERC MY2021: 0 fixes without it (docs/app.md)
    pair_landmarks: bool = True
    single_radius_m: Positive = 25.0
    # The two of a pair are looked for within pair_radius_m of the rover (None: single_radius_m).
    # Their separation's gate does not widen with the rover's drift, and the fix's covariance
    # carries the lever arm from the pair to the rover (fix_from_pair), so a pair may lie farther
    # than one landmark alone: craters tens of metres apart (sparse-5km) rarely lie two within 25 m.
    # 80 m for craters changed nothing on sparse-5km seed 1 (docs/craters.md): off by default
    pair_radius_m: Positive | None = None
    single_gate_chi2: Positive = 13.82  # 99.9 % of a 2-dof chi-square
    single_max_false_alarm: Annotated[float, Interval(gt=0, lt=1)] = 1e-3
    single_density_radius_m: Positive = 200.0
    single_sigma_yaw_rad: Positive = 0.5  # the fix's heading sigma: no heading information
    # An identified landmark's catalog entry is placed to the matcher's sigma_m per axis, and a
    # big one no better than a fraction of its size: an orbital crater's centre to ~0.06 D per
    # axis (the detector's centre error, mean 0.075 D radial, docs/detectors.md). The single and
    # pair identifications (their gates, chance odds and fixes) take hypot(sigma_m, this x size)
    # per entry (fgslam.match_to_fix.catalog_sigma); 0: sigma_m for every size (rocks). With the
    # matcher's 0.3 m for every crater, one 8.2 m crater whose catalog centre was 1.7 m off (0.21 D)
    # gave single fixes claiming 0.58 m and took iSAM2 from 0.33 to 1.37 m off on sparse-5km
    # (docs/craters.md)
    catalog_sigma_rel: NonNegative = 0.0
    # A single or pair fix names its landmarks and catalog entries (GlobalFix.anchors), so that a
    # back-end puts the entries on the landmarks, once, instead of the pose at every fix: n fixes
    # on one entry otherwise add 1 + 1/2 + ... + 1/n fixes' information about the error they
    # share. A landmark whose map says it is anchored already (LandmarkMap.catalog_row) is not
    # identified again. Off by default: on sparse-5km's first 2.5 km, craters anchored left the
    # smoother 1.6-2.7 m off where their pose fixes gave 0.97 m (docs/craters.md, "Catalog
    # anchors, measured": once the rover's sigma passes ~0.5 m no crater alone passes the
    # identification's chance bound again, and an anchor is never retracted).
    anchor_landmarks: bool = False
    # An anchor's covariance is the entry's own error alone, per axis hypot(anchor_sigma_m,
    # catalog_sigma_rel x size) (times the correlation factor): the rover's side (its rim fit, its
    # map) is the back-end's own, so neither the matcher's sigma_m nor inflation enters. 0.2 m:
    # half a pixel of a 0.25-0.3 m orbital image and its georeference; the matcher's 0.3 m
    # inflated 1.75x for a 3 m crater (0.61 m) was taken at 2.3x the entry's error and, counted
    # once, left the smoother 1.6 m off on sparse-5km (docs/craters.md, "Catalog anchors")
    anchor_sigma_m: NonNegative = 0.2
    matcher: dict = field(default_factory=dict)  # overrides of the matcher's config

    def __post_init__(self) -> None:
        if self.anchor_landmarks and self.anchor_sigma_m == 0 and self.catalog_sigma_rel == 0:
            raise RelocalizerError("relocalizer: anchor_landmarks needs anchor_sigma_m or catalog_sigma_rel above 0 "
                                   "(an anchor's covariance would be zero)")
        if not self.matcher:
            return
        from reloc.config import config_from_dict
        from reloc.matcher import MatcherConfig

        try:  # the matcher's overrides are checked with the config, not at the first attempt
            config_from_dict(MatcherConfig, self.matcher, where="matcher.")
        except ConfigError as exc:
            raise RelocalizerError(f"relocalizer: {exc}") from None

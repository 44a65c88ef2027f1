"""Relocalizer: match the back-end's local landmark map against the orbital catalog and turn the
matched similarity into a late global pose fix.

The constellation matcher returns ``world = s * R(theta) @ local + t`` for the map snapshot taken at
``t_meas``. Applied to the back-end's own pose estimate at that instant, it gives the rover's
global (x, y, yaw): ``xy = s R xy_est + t``, ``yaw = yaw_est + theta``. The fix covariance comes
from the inlier geometry (Procrustes): with per-point sigma ``sigma`` (the match RMSE corrected for
the fitted degrees of freedom, floored, inflated) and N inliers spread ``S = sum |l_i - c|^2``
around their centroid c, the translation at c has variance sigma^2/N and the rotation
sigma^2/S; the rover at offset d from c inherits ``sigma^2/N I + sigma^2/S perp(d) perp(d)^T``
and the matching x/y-yaw cross terms. The estimate's own map uncertainty enters through the
landmarks' mean planar covariance (scaled by ``map_cov_weight``), divided by N.

The fix reaches the back-end at ``t_recv = t_meas + latency``: the measured matching time
(``latency="measured"``, times ``latency_scale``) or a configured delay (``latency="fixed"``,
the default, so runs are reproducible).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from fgslam.errors import FgslamError
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.geometry import wrap_angle
from reloc.measurements import GlobalFix, RockCatalog

log = logging.getLogger(__name__)


class RelocalizerError(FgslamError):
    """Bad relocalizer configuration or input."""


@dataclass(frozen=True)
class RelocalizerConfig:
    """When and how the local map is matched, and how a match becomes a fix (defaults in code)."""

    # one attempt per period of stream time (goal: fixes >= 0.2 Hz; cnes: 0.147 Hz at 3 s, 0.219 at 2 s)
    period_s: float = 2.0
    min_obs: int = 2  # landmarks seen fewer times are not matched (likely false positives)
    min_landmarks: int = 8  # skip the attempt below this many usable landmarks
    max_landmarks: int = 160  # this many landmarks form the local constellation ...
    max_radius_m: float = 30.0  # ... chosen within this distance of the rover ...
    # ... "largest" first (the orbital catalog holds mostly the larger rocks: on a dense yard the
    # nearest 80 are small rocks in a few metres, few of them catalogued) or "nearest" first
    select: str = "largest"
    # an attempt is skipped while the rover has moved less than min_travel_m and turned less than
    # min_turn_deg since the last one (standing still, its map and pose say nothing new: my2021,
    # 687 -> 554 attempts, the same ATE, 44 -> 48x real time); both 0: never skipped
    min_travel_m: float = 0.05
    min_turn_deg: float = 3.0
    latency: str = "fixed"  # "fixed": t_recv = t_meas + delay_s; "measured": + matching wall time
    delay_s: float = 2.0
    latency_scale: float = 1.0  # multiplies the measured matching time (slower onboard CPU)
    sigma_floor_m: float = 0.05  # per-point residual sigma never below this
    sigma_yaw_floor_rad: float = 0.003
    inflation: float = 1.75  # multiplies the residual sigma (unmodelled map distortion)
    map_cov_weight: float = 0.0  # weight of the landmarks' own planar covariance in sigma^2
    # The fix describes the rover, so the final fit weighs each matched rock by how well the map
    # ties it to the rover: w = 1 / (1 + (d / fit_radius_m)^2) at distance d from the rover (a
    # relative map error that grows with distance and equals the catalog's at fit_radius_m),
    # covariance from the weighted fit. None: every inlier alike (the matcher's own fit). Seed 0,
    # iSAM2 + reloc, None -> 10: my2020 0.040 -> 0.034 m, my2021 0.034 -> 0.030, my2022 0.036 ->
    # 0.032, cnes 0.060 -> 0.057; my2020 seed 2 0.166 m / 62 % inside 3 sigma -> 0.060 m / 96 %
    # (a map bent on a climb gave fixes biased with it); docs/app.md
    fit_radius_m: float | None = 10.0
    max_scale_error: float = 0.05  # reject matches whose scale is further than this from 1
    # Search prior: the map's centroid must land within prior_min_radius_m + prior_sigmas *
    # sigma_pos (largest std of the estimate's x/y) of where the estimate puts it; None: no prior.
    # Successive fixes share most inlier rocks, hence most of their catalog error: fusing them as
    # independent would make a back-end overconfident. correlation "rocks" (default): each fix's
    # covariance is multiplied by 1 + the mean, over its inlier catalog rocks, of how many earlier
    # fixes used that rock (sum over earlier fixes of the fraction of rocks shared with them; for
    # fixes on the same rocks the covariance-intersection bound, whenever they were made).
    # "window": 1 + number of fixes produced in the preceding correlation_window_s. "none": 1.
    correlation: str = "rocks"
    correlation_window_s: float = 60.0
    prior_sigmas: float | None = 6.0
    prior_min_radius_m: float = 3.0
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
    crop_margin_m: float = 2.0
    # Crops are cut on a grid: centre snapped to crop_snap_m, radius rounded up to a multiple of
    # it (plus the snapping error), so successive attempts a few decimetres apart share one crop
    # and its index, kept in a cache of crop_cache crops. The crop still holds every rock that
    # can hold the map.
    crop_snap_m: float = 2.0
    crop_cache: int = 8
    matcher: dict = field(default_factory=dict)  # overrides of the matcher's config

    def __post_init__(self) -> None:
        if self.period_s <= 0:
            raise RelocalizerError(f"relocalizer period_s must be > 0, got {self.period_s}")
        if self.latency not in ("fixed", "measured"):
            raise RelocalizerError(f"relocalizer latency must be 'fixed' or 'measured', got {self.latency!r}")
        if self.delay_s < 0:
            raise RelocalizerError(f"relocalizer delay_s must be >= 0, got {self.delay_s}")
        if self.select not in ("largest", "nearest"):
            raise RelocalizerError(f"relocalizer select must be 'largest' or 'nearest', got {self.select!r}")
        if self.correlation not in ("rocks", "window", "none"):
            raise RelocalizerError(
                f"relocalizer correlation must be 'rocks', 'window' or 'none', got {self.correlation!r}")
        if self.fit_radius_m is not None and not self.fit_radius_m > 0:
            raise RelocalizerError(f"relocalizer fit_radius_m must be > 0 or null, got {self.fit_radius_m}")
        if not self.crop_snap_m > 0 or self.crop_cache < 1:
            raise RelocalizerError(
                f"relocalizer crop_snap_m must be > 0 and crop_cache >= 1, got {self.crop_snap_m}, {self.crop_cache}")


@dataclass(frozen=True)
class FixAttempt:
    """One matching attempt at ``t_meas``: ``status`` is "fix", "no match", "too few landmarks" or
    "bad scale"; ``fix`` is set for "fix". ``local_xy``/``world_xy`` (K, 2) are the matched pairs
    (local map in estimated world, catalog) for display; ``match_time_s`` is the wall time;
    ``tracked``: the match is the estimate's own pose, verified (``RelocalizerConfig.track``)."""

    t_meas: float
    n_landmarks: int
    status: str
    match_time_s: float
    fix: GlobalFix | None = None
    local_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    world_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    est_xyyaw: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tracked: bool = False


def select_local_map(lmap: LandmarkMap, xy_rover: np.ndarray, cfg: RelocalizerConfig) -> np.ndarray:
    """Indices of the landmarks used for matching: n_obs >= min_obs within ``max_radius_m`` of the
    rover, at most ``max_landmarks`` of them, the largest (or the nearest, ``cfg.select``) first."""
    if len(lmap) == 0:
        return np.zeros(0, dtype=int)
    ok = np.flatnonzero(lmap.n_obs >= cfg.min_obs)
    d = np.linalg.norm(lmap.xyz_world_m[ok, :2] - np.asarray(xy_rover)[:2], axis=1)
    ok, d = ok[d <= cfg.max_radius_m], d[d <= cfg.max_radius_m]
    if cfg.select == "largest":
        order = np.lexsort((d, -lmap.size_m[ok]))  # larger first, nearer among equals
    else:
        order = np.argsort(d, kind="stable")
    return np.sort(ok[order[: cfg.max_landmarks]])


def fix_from_similarity(
    est: PoseEstimate,
    rotation_rad: float,
    translation: np.ndarray,
    scale: float,
    local_inliers_xy: np.ndarray,
    rmse_m: float,
    cfg: RelocalizerConfig,
    t_recv: float,
    map_var_m2: float = 0.0,
    similarity_cov: np.ndarray | None = None,
    cov_scale: float = 1.0,
) -> GlobalFix:
    """Rover fix at ``est.t`` from a local->world similarity and its inliers (K, 2) in the local (estimated world) frame.

    With ``similarity_cov`` (4, 4) over (tx_m, ty_m, theta_rad, scale) from the matcher, the fix
    covariance is its first-order propagation through xy = s R xy_est + t, yaw = yaw_est + theta
    (times ``inflation``^2, plus the map term); otherwise the inlier-geometry formula of the
    module doc is used."""
    L = np.asarray(local_inliers_xy, float).reshape(-1, 2)
    n = L.shape[0]
    if n < 3:
        raise RelocalizerError(f"a fix needs at least 3 inliers, got {n}")
    c, s = np.cos(rotation_rad), np.sin(rotation_rad)
    R = np.array([[c, -s], [s, c]])
    t = np.asarray(translation, float).reshape(2)
    xy_est = est.position_m[:2]
    xy = scale * R @ xy_est + t
    yaw = float(wrap_angle(est.yaw_rad + rotation_rad))
    dof_corr = n / max(n - 4, 1)  # 4 fitted parameters (similarity) shrink the residuals
    sigma2 = max(rmse_m**2 * dof_corr + cfg.map_cov_weight * map_var_m2, cfg.sigma_floor_m**2)
    sigma2 *= cfg.inflation**2
    centroid = L.mean(axis=0)
    spread = float(np.sum((L - centroid) ** 2))
    var_yaw = max(sigma2 / max(spread, 1e-9), cfg.sigma_yaw_floor_rad**2)
    d_world = R @ (xy_est - centroid)
    perp = np.array([-d_world[1], d_world[0]])
    cov = np.zeros((3, 3))
    if similarity_cov is not None and np.all(np.isfinite(similarity_cov)):
        J = np.zeros((3, 4))
        J[:2, :2] = np.eye(2)
        J[:2, 2] = scale * np.array([[-s, -c], [c, -s]]) @ xy_est
        J[:2, 3] = R @ xy_est
        J[2, 2] = 1.0
        cov = cfg.inflation**2 * (J @ np.asarray(similarity_cov, float) @ J.T)
        cov[:2, :2] += (cfg.inflation**2 * cfg.map_cov_weight * map_var_m2 / n + cfg.sigma_floor_m**2 / n) * np.eye(2)
        cov[2, 2] = max(cov[2, 2], cfg.sigma_yaw_floor_rad**2)
        cov = 0.5 * (cov + cov.T)
    else:
        cov[:2, :2] = sigma2 / n * np.eye(2) + var_yaw * np.outer(perp, perp)
        cov[:2, 2] = cov[2, :2] = var_yaw * perp
        cov[2, 2] = var_yaw
    return GlobalFix(
        t_meas=est.t, t_recv=t_recv, x_m=float(xy[0]), y_m=float(xy[1]), yaw_rad=yaw,
        cov_xyyaw=cov * cov_scale, n_inliers=n, rmse_m=float(rmse_m),
    )


def rover_weighted_fit(
    local_xy: np.ndarray, world_xy: np.ndarray, rover_xy: np.ndarray, radius_m: float, floor_sigma_m: float
):
    """Rigid re-fit of matched pairs (K, 2) weighted by closeness to the rover, ``w = 1 / (1 +
    (d / radius_m)^2)`` (``RelocalizerConfig.fit_radius_m``): (rotation_rad, translation (2,),
    scale 1, weighted RMSE m, (4, 4) covariance over (tx, ty, theta, scale), residual sigma
    floored at ``floor_sigma_m``)."""
    from reloc.match_result import similarity_covariance
    from reloc.procrustes import umeyama_2d

    d2 = np.sum((local_xy - np.asarray(rover_xy, float)) ** 2, axis=1)
    w = 1.0 / (1.0 + d2 / radius_m**2)
    sim = umeyama_2d(local_xy, world_xy, w, with_scale=False)
    res = sim.apply(local_xy) - world_xy
    rmse = float(np.sqrt(np.sum(w * np.sum(res * res, axis=1)) / np.sum(w)))
    cov = similarity_covariance(sim, local_xy, world_xy, floor_sigma_m=floor_sigma_m, with_scale=False, weights=w)
    return float(sim.theta_rad), np.asarray(sim.translation, float), 1.0, rmse, cov


class Relocalizer:
    """Matches map snapshots against a catalog (``reloc.ConstellationMatcher`` unless one is given)."""

    def __init__(self, catalog: RockCatalog, config: RelocalizerConfig | None = None, matcher=None) -> None:
        self.config = config or RelocalizerConfig()
        self.catalog = catalog
        if matcher is None:
            from reloc.catalog import Catalog
            from reloc.config import config_from_dict
            from reloc.matcher import ConstellationMatcher, MatcherConfig

            mcfg = config_from_dict(MatcherConfig, dict(self.config.matcher), where="matcher.")
            t0 = time.perf_counter()
            matcher = ConstellationMatcher(Catalog(catalog.xy_m, catalog.size_m), mcfg)
            self.build_time_s = time.perf_counter() - t0
            self._mcfg = mcfg
        else:
            self.build_time_s = 0.0
            self._mcfg = None  # a given matcher is used as it is (no crops)
        self.matcher = matcher
        mc = getattr(matcher, "config", None)  # a given matcher may not have a MatcherConfig
        self._fit_floor_sigma_m = float(getattr(mc, "fit_floor_sigma_m", 0.0))
        self._fix_times: list[float] = []
        self._last_xyyaw: np.ndarray | None = None  # pose of the last attempt
        self._rock_uses = np.zeros(len(catalog.xy_m), dtype=np.int64)  # fixes that used each catalog rock
        self._crops: dict[tuple[int, int, int], tuple[np.ndarray, object]] = {}  # insertion order = LRU
        self.n_crops_built = 0

    def wants(self, est: PoseEstimate) -> bool:
        """Whether an attempt at ``est`` is worth making: the rover has moved ``min_travel_m`` or
        turned ``min_turn_deg`` since the last attempt (always for the first one)."""
        cfg = self.config
        if self._last_xyyaw is None or (cfg.min_travel_m <= 0 and cfg.min_turn_deg <= 0):
            return True
        d = float(np.hypot(*(est.position_m[:2] - self._last_xyyaw[:2])))
        dyaw = abs(float(wrap_angle(est.yaw_rad - self._last_xyyaw[2])))
        return d >= cfg.min_travel_m or np.degrees(dyaw) >= cfg.min_turn_deg

    def attempt(self, lmap: LandmarkMap, est: PoseEstimate) -> FixAttempt:
        """Try to relocalize the map snapshot taken with pose ``est`` (its ``t`` is ``t_meas``)."""
        cfg = self.config
        est_xyyaw = np.array([est.position_m[0], est.position_m[1], est.yaw_rad])
        self._last_xyyaw = est_xyyaw
        idx = select_local_map(lmap, est.position_m, cfg)
        if idx.size < cfg.min_landmarks:
            return FixAttempt(est.t, int(idx.size), "too few landmarks", 0.0, est_xyyaw=est_xyyaw)
        local_xy = lmap.xyz_world_m[idx, :2]
        t0 = time.perf_counter()
        prior = None
        if cfg.prior_sigmas is not None:
            from reloc.matcher import MatchPrior
            from reloc.procrustes import Similarity2D

            sigma_pos = float(np.sqrt(max(np.linalg.eigvalsh(est.cov[:2, :2])[-1], 0.0)))
            guess = Similarity2D(0.0, np.zeros(2), 1.0) if cfg.track else None
            prior = MatchPrior(local_xy.mean(axis=0), cfg.prior_min_radius_m + cfg.prior_sigmas * sigma_pos, guess)
        rows = None  # catalog rows of the matcher's catalog (None: the whole catalog)
        if prior is None:
            result = self.matcher.match(local_xy, lmap.size_m[idx])
        elif cfg.crop_catalog and self._mcfg is not None:
            result, rows = self._match_cropped(local_xy, lmap.size_m[idx], prior)
        else:
            result = self.matcher.match(local_xy, lmap.size_m[idx], prior)
        dt = time.perf_counter() - t0
        if result is None:
            return FixAttempt(est.t, int(idx.size), "no match", dt, est_xyyaw=est_xyyaw)
        if abs(float(result.scale) - 1.0) > cfg.max_scale_error:
            log.info("t=%.1f s: match rejected, scale %.3f", est.t, result.scale)
            return FixAttempt(est.t, int(idx.size), "bad scale", dt, est_xyyaw=est_xyyaw)
        pairs = np.asarray(result.inlier_pairs, dtype=int).reshape(-1, 2).copy()
        if rows is not None:
            pairs[:, 1] = rows[pairs[:, 1]]
        L = local_xy[pairs[:, 0]]
        W = self.catalog.xy_m[pairs[:, 1]]
        latency = cfg.delay_s if cfg.latency == "fixed" else dt * cfg.latency_scale
        rotation, translation, scale = float(result.rotation_rad), np.asarray(result.translation), float(result.scale)
        rmse, sim_cov = float(result.rmse_m), getattr(result, "similarity_cov", None)
        if cfg.fit_radius_m is not None:
            rotation, translation, scale, rmse, sim_cov = rover_weighted_fit(
                L, W, est.position_m[:2], cfg.fit_radius_m, self._fit_floor_sigma_m)
        cov_lm = lmap.cov_world_m2[idx[pairs[:, 0]]]
        map_var = float(np.mean(0.5 * (cov_lm[:, 0, 0] + cov_lm[:, 1, 1]))) if len(cov_lm) else 0.0
        try:
            fix = fix_from_similarity(
                est, rotation, translation, scale, L, rmse, cfg, t_recv=est.t + latency, map_var_m2=map_var,
                similarity_cov=sim_cov,
                cov_scale=self._correlation_scale(est.t, pairs[:, 1]),
            )
        except RelocalizerError as exc:
            return FixAttempt(est.t, int(idx.size), f"no match ({exc})", dt, est_xyyaw=est_xyyaw)
        self._fix_times.append(est.t)
        np.add.at(self._rock_uses, np.unique(pairs[:, 1]), 1)
        return FixAttempt(est.t, int(idx.size), "fix", dt, fix, L, W, est_xyyaw, bool(getattr(result, "from_guess", False)))

    def _match_cropped(self, local_xy: np.ndarray, local_size: np.ndarray, prior):
        """Match against the catalog rocks that can hold the map under ``prior``; returns the
        result (catalog indices local to the crop) and the crop's rows in the full catalog."""
        rows, sub = self._crop(prior.center_xy, prior.radius_m + self._extent(local_xy) + self.config.crop_margin_m)
        if sub is None:
            return None, rows
        return sub.match(local_xy, local_size, prior), rows

    @staticmethod
    def _extent(local_xy: np.ndarray) -> float:
        return float(np.max(np.linalg.norm(local_xy - local_xy.mean(axis=0), axis=1)))

    def _crop(self, center_xy, radius_m: float):
        """Rows (sorted) and matcher of the grid crop that covers the disc (``center_xy``, ``radius_m``);
        the matcher is None when the crop cannot be indexed (too few rocks, degenerate)."""
        from reloc.catalog import Catalog, CatalogConfig
        from reloc.errors import RelocError
        from reloc.matcher import ConstellationMatcher

        snap = self.config.crop_snap_m
        key = (*np.round(np.asarray(center_xy, float) / snap).astype(int).tolist(), int(np.ceil(radius_m / snap)))
        hit = self._crops.pop(key, None)
        if hit is None:
            center = np.array(key[:2], float) * snap
            # the snapped centre is at most snap/sqrt(2) from the asked one
            radius = key[2] * snap + snap / np.sqrt(2.0)
            rows = np.sort(np.asarray(self.matcher.catalog.tree.query_ball_point(center, radius), dtype=int))
            sub = None
            if rows.size >= 3:
                try:  # a small index: one thread (spawning workers costs more than the queries)
                    cat = Catalog(self.catalog.xy_m[rows], self.catalog.size_m[rows], CatalogConfig(workers=1))
                    sub = ConstellationMatcher(cat, self._mcfg)
                except RelocError as exc:  # a degenerate crop (duplicates, collinear): nothing to match
                    log.debug("catalog crop of %d rocks not usable: %s", rows.size, exc)
            hit = (rows, sub)
            self.n_crops_built += 1
        self._crops[key] = hit  # most recently used last
        while len(self._crops) > self.config.crop_cache:
            self._crops.pop(next(iter(self._crops)))
        return hit

    def _correlation_scale(self, t: float, catalog_rows: np.ndarray) -> float:
        """Covariance multiplier of a fix at ``t`` whose inliers are catalog rocks ``catalog_rows``
        (see ``RelocalizerConfig.correlation``)."""
        cfg = self.config
        if cfg.correlation == "rocks":
            return 1.0 + float(np.mean(self._rock_uses[np.unique(catalog_rows)]))
        if cfg.correlation == "window" and cfg.correlation_window_s > 0:
            w = cfg.correlation_window_s
            return 1.0 + sum(1 for tf in self._fix_times if t - w <= tf < t)
        return 1.0

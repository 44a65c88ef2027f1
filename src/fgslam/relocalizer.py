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
from reloc.measurements import GlobalFix, RockCatalog

log = logging.getLogger(__name__)


class RelocalizerError(FgslamError):
    """Bad relocalizer configuration or input."""


@dataclass(frozen=True)
class RelocalizerConfig:
    """When and how the local map is matched, and how a match becomes a fix (defaults in code)."""

    period_s: float = 3.0  # one attempt per period of stream time (goal: fixes >= 0.2 Hz)
    min_obs: int = 2  # landmarks seen fewer times are not matched (likely false positives)
    min_landmarks: int = 8  # skip the attempt below this many usable landmarks
    max_landmarks: int = 80  # the nearest landmarks to the rover form the local constellation
    max_radius_m: float = 20.0  # ... within this distance of the rover
    latency: str = "fixed"  # "fixed": t_recv = t_meas + delay_s; "measured": + matching wall time
    delay_s: float = 2.0
    latency_scale: float = 1.0  # multiplies the measured matching time (slower onboard CPU)
    sigma_floor_m: float = 0.05  # per-point residual sigma never below this
    sigma_yaw_floor_rad: float = 0.003
    inflation: float = 1.75  # multiplies the residual sigma (unmodelled map distortion)
    map_cov_weight: float = 0.0  # weight of the landmarks' own planar covariance in sigma^2
    max_scale_error: float = 0.05  # reject matches whose scale is further than this from 1
    # Search prior: the map's centroid must land within prior_min_radius_m + prior_sigmas *
    # sigma_pos (largest std of the estimate's x/y) of where the estimate puts it; None: no prior.
    # Successive fixes share most inlier rocks, hence most of their catalog error: fusing them as
    # independent would make a back-end overconfident. Each fix's covariance is multiplied by
    # 1 + (fixes produced in the preceding window), so the fixes of a window together carry about
    # the information of one (the covariance-intersection bound). 0 disables.
    correlation_window_s: float = 60.0
    prior_sigmas: float | None = 6.0
    prior_min_radius_m: float = 3.0
    # With a prior, match against the catalog rocks that can hold the map (within prior radius +
    # the map's extent + crop_margin_m of where the estimate puts it): a small index built per
    # attempt (a few ms) instead of hypotheses over the whole catalog. False: whole catalog.
    crop_catalog: bool = True
    crop_margin_m: float = 2.0
    matcher: dict = field(default_factory=dict)  # overrides of the matcher's config

    def __post_init__(self) -> None:
        if self.period_s <= 0:
            raise RelocalizerError(f"relocalizer period_s must be > 0, got {self.period_s}")
        if self.latency not in ("fixed", "measured"):
            raise RelocalizerError(f"relocalizer latency must be 'fixed' or 'measured', got {self.latency!r}")
        if self.delay_s < 0:
            raise RelocalizerError(f"relocalizer delay_s must be >= 0, got {self.delay_s}")


@dataclass(frozen=True)
class FixAttempt:
    """One matching attempt at ``t_meas``: ``status`` is "fix", "no match", "too few landmarks" or
    "bad scale"; ``fix`` is set for "fix". ``local_xy``/``world_xy`` (K, 2) are the matched pairs
    (local map in estimated world, catalog) for display; ``match_time_s`` is the wall time."""

    t_meas: float
    n_landmarks: int
    status: str
    match_time_s: float
    fix: GlobalFix | None = None
    local_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    world_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    est_xyyaw: np.ndarray = field(default_factory=lambda: np.zeros(3))


def select_local_map(lmap: LandmarkMap, xy_rover: np.ndarray, cfg: RelocalizerConfig) -> np.ndarray:
    """Indices of the landmarks used for matching: n_obs >= min_obs, nearest ``max_landmarks`` within ``max_radius_m``."""
    if len(lmap) == 0:
        return np.zeros(0, dtype=int)
    ok = np.flatnonzero(lmap.n_obs >= cfg.min_obs)
    d = np.linalg.norm(lmap.xyz_world_m[ok, :2] - np.asarray(xy_rover)[:2], axis=1)
    ok, d = ok[d <= cfg.max_radius_m], d[d <= cfg.max_radius_m]
    return ok[np.argsort(d, kind="stable")[: cfg.max_landmarks]]


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
    yaw = float(np.arctan2(np.sin(est.yaw_rad + rotation_rad), np.cos(est.yaw_rad + rotation_rad)))
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
        self._fix_times: list[float] = []

    def attempt(self, lmap: LandmarkMap, est: PoseEstimate) -> FixAttempt:
        """Try to relocalize the map snapshot taken with pose ``est`` (its ``t`` is ``t_meas``)."""
        cfg = self.config
        est_xyyaw = np.array([est.position_m[0], est.position_m[1], est.yaw_rad])
        idx = select_local_map(lmap, est.position_m, cfg)
        if idx.size < cfg.min_landmarks:
            return FixAttempt(est.t, int(idx.size), "too few landmarks", 0.0, est_xyyaw=est_xyyaw)
        local_xy = lmap.xyz_world_m[idx, :2]
        t0 = time.perf_counter()
        prior = None
        if cfg.prior_sigmas is not None:
            from reloc.matcher import MatchPrior

            sigma_pos = float(np.sqrt(max(np.linalg.eigvalsh(est.cov[:2, :2])[-1], 0.0)))
            prior = MatchPrior(local_xy.mean(axis=0), cfg.prior_min_radius_m + cfg.prior_sigmas * sigma_pos)
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
        cov_lm = lmap.cov_world_m2[idx[pairs[:, 0]]]
        map_var = float(np.mean(0.5 * (cov_lm[:, 0, 0] + cov_lm[:, 1, 1]))) if len(cov_lm) else 0.0
        try:
            fix = fix_from_similarity(
                est, float(result.rotation_rad), np.asarray(result.translation), float(result.scale),
                L, float(result.rmse_m), cfg, t_recv=est.t + latency, map_var_m2=map_var,
                similarity_cov=getattr(result, "similarity_cov", None),
                cov_scale=self._correlation_scale(est.t),
            )
        except RelocalizerError as exc:
            return FixAttempt(est.t, int(idx.size), f"no match ({exc})", dt, est_xyyaw=est_xyyaw)
        self._fix_times.append(est.t)
        return FixAttempt(est.t, int(idx.size), "fix", dt, fix, L, W, est_xyyaw)

    def _match_cropped(self, local_xy: np.ndarray, local_size: np.ndarray, prior):
        """Match against the catalog rocks that can hold the map under ``prior``; returns the
        result (catalog indices local to the crop) and the crop's rows in the full catalog."""
        from reloc.catalog import Catalog
        from reloc.errors import RelocError
        from reloc.matcher import ConstellationMatcher

        extent = float(np.max(np.linalg.norm(local_xy - local_xy.mean(axis=0), axis=1)))
        radius = prior.radius_m + extent + self.config.crop_margin_m
        rows = np.asarray(self.matcher.catalog.tree.query_ball_point(np.asarray(prior.center_xy, float), radius), dtype=int)
        rows.sort()
        if rows.size < 3:
            return None, rows
        try:
            sub = ConstellationMatcher(Catalog(self.catalog.xy_m[rows], self.catalog.size_m[rows]), self._mcfg)
        except RelocError as exc:  # a degenerate crop (duplicates, collinear): nothing to match
            log.debug("catalog crop of %d rocks not usable: %s", rows.size, exc)
            return None, rows
        return sub.match(local_xy, local_size, prior), rows

    def _correlation_scale(self, t: float) -> float:
        """1 + number of fixes produced within ``correlation_window_s`` before ``t``."""
        w = self.config.correlation_window_s
        if w <= 0:
            return 1.0
        return 1.0 + sum(1 for tf in self._fix_times if t - w <= tf < t)

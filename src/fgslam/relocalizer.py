"""The rock kind's relocalizer: match the back-end's local rock map against the orbital rock
catalog and turn the matched similarity into a late global pose fix. Another kind brings its own
(``LandmarkKind.relocalizer``, a factory ``(catalog, config)``; see
:class:`fgslam.fix_sources.FixProducer` for what the runner asks of one).

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

import dataclasses
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fgslam.backends.reanchor import is_lost
from fgslam.local_window import LocalMapWindow
from fgslam.match_to_fix import (
    catalog_box_of,
    catalog_sigma,
    fix_from_pair,
    fix_from_similarity,
    fix_from_single,
    identify_pair,
    identify_single,
    rover_relative_cov_xy,
    rover_weighted_fit,
    rover_weights,
    select_local_map,
)
from fgslam.relocalizer_config import RelocalizerConfig, RelocalizerError
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.covariance import distance_correlation_scale
from reloc.geometry import wrap_angle
from reloc.measurements import CatalogAnchor, GlobalFix, RockCatalog

log = logging.getLogger(__name__)

__all__ = [
    "FixAttempt", "Relocalizer", "RelocalizerConfig", "RelocalizerError", "StaleMapCheck", "fix_from_similarity",
    "rover_weighted_fit", "select_local_map",
]


class StaleMapCheck:
    """Whether fewer than ``min_new`` landmark observations joined a map since the previous look
    (never at the first one; ``min_new`` 0: never); it remembers each map's counts for the next."""

    def __init__(self, min_new: int) -> None:
        self.min_new = min_new
        self._last: dict[int, int] | None = None  # landmark id -> observations, at the last look

    def stale(self, lmap: LandmarkMap) -> bool:
        counts = dict(zip(lmap.ids.tolist(), lmap.n_obs.tolist()))
        last, self._last = self._last, counts
        if last is None or self.min_new == 0:
            return False
        return sum(n - last.get(i, 0) for i, n in counts.items() if n > last.get(i, 0)) < self.min_new


@dataclass(frozen=True)
class FixAttempt:
    """One matching attempt at ``t_meas``: ``status`` is "fix", "no match", "too few landmarks",
    "stale map" (too few new observations of the map since the last attempt) or "bad scale";
    ``fix`` is set for "fix". ``local_xy``/``world_xy`` (K, 2) are the matched pairs
    (local map in estimated world, catalog) for display; ``match_time_s`` is the wall time;
    ``tracked``: the match is the estimate's own pose, verified (``RelocalizerConfig.track``);
    ``source``: the relocalizer that made it (its kinds, "+"-joined); ``single``: a fix from one
    or two landmarks identified without a constellation match, with ``false_alarm`` its
    wrong-identification bound."""

    t_meas: float
    n_landmarks: int
    status: str
    match_time_s: float
    fix: GlobalFix | None = None
    local_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    world_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    est_xyyaw: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tracked: bool = False
    source: str = ""
    single: bool = False  # a fix from one or two landmarks identified without a match (single_landmark, pair_landmarks)
    false_alarm: float = 0.0  # its bound: the odds that a chance catalog entry lies that close


class Relocalizer:
    """Matches snapshots of the map of ``kind`` (rocks) against a catalog of that kind
    (``reloc.ConstellationMatcher`` unless one is given)."""

    def __init__(self, catalog: RockCatalog, config: RelocalizerConfig | dict | None = None, matcher=None,
                 kind: str = "rocks") -> None:
        if isinstance(config, dict):  # overrides, e.g. from a YAML file
            from reloc.config import config_from_dict

            config = config_from_dict(RelocalizerConfig, config, where="relocalizer.")
        self.config = config or RelocalizerConfig()
        self.kinds = (kind,)
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
        sizes = np.asarray(catalog.size_m, dtype=float)
        sizes = sizes[np.isfinite(sizes) & (sizes > 0)]
        # the local map leaves out what the catalog cannot hold (RelocalizerConfig.min_size_fraction)
        self.min_size_m = float(self.config.min_size_fraction * np.quantile(sizes, 0.01)) if sizes.size else 0.0
        self._fix_times: list[float] = []
        self._last_xyyaw: np.ndarray | None = None  # pose of the last attempt
        self._path_m = 0.0  # planar path between the attempts' poses, summed
        self._fix_path_m: float | None = None  # _path_m at the last fix
        self._fresh = StaleMapCheck(self.config.min_new_observations)
        self._misses = 0  # consecutive attempts that matched nothing (the period's backoff)
        self._rock_uses = np.zeros(len(catalog.xy_m), dtype=np.int64)  # fixes that used each catalog rock
        self._crops: dict[tuple[int, int, int], tuple[np.ndarray, object]] = {}  # insertion order = LRU
        self.n_crops_built = 0
        self._single_tree = None  # KD-tree of the catalog for single-landmark fixes, built at first use
        self._single_box = None  # and the catalog's bounding box (the chance density's area)
        self.window = (LocalMapWindow(self.config.window_path_m, self.config.window_max_kept)
                       if self.config.window_path_m > 0 else None)

    @property
    def period_s(self) -> float:
        """Stream time between attempts: ``period_s``, doubled per miss beyond ``backoff_after``
        consecutive ones, at most ``backoff_max_period_s`` (see :class:`RelocalizerConfig`)."""
        cfg = self.config
        extra = self._misses - cfg.backoff_after
        if cfg.backoff_after == 0 or extra < 0:
            return cfg.period_s
        return min(cfg.period_s * 2.0 ** min(extra + 1, 30), max(cfg.backoff_max_period_s, cfg.period_s))

    def wants(self, est: PoseEstimate) -> bool:
        """Whether an attempt at ``est`` is worth making: the rover has moved ``min_travel_m`` or
        turned ``min_turn_deg`` since the last attempt (always for the first one)."""
        cfg = self.config
        if self._last_xyyaw is None or (cfg.min_travel_m <= 0 and cfg.min_turn_deg <= 0):
            return True
        d = float(np.hypot(*(est.position_m[:2] - self._last_xyyaw[:2])))
        dyaw = abs(float(wrap_angle(est.yaw_rad - self._last_xyyaw[2])))
        return d >= cfg.min_travel_m or np.degrees(dyaw) >= cfg.min_turn_deg

    def attempt(self, maps: Mapping[str, LandmarkMap] | LandmarkMap, est: PoseEstimate) -> FixAttempt:
        """Try to relocalize the map snapshot taken with pose ``est`` (its ``t`` is ``t_meas``);
        ``maps`` is the snapshot of every kind by name (this one reads its own), or its map."""
        lmap = maps if isinstance(maps, LandmarkMap) else maps[self.kinds[0]]
        if lmap.kind != self.kinds[0]:
            raise RelocalizerError(f"the {self.kinds[0]} relocalizer was given a map of {lmap.kind!r}")
        att = self._attempt(lmap, est)
        if att.status == "fix":
            self._misses = 0
        elif att.status.startswith(("no match", "bad scale")):
            self._misses += 1
        return att if att.source else dataclasses.replace(att, source=self.kinds[0])

    def _attempt(self, lmap: LandmarkMap, est: PoseEstimate) -> FixAttempt:
        cfg = self.config
        est_xyyaw = np.array([est.position_m[0], est.position_m[1], est.yaw_rad])
        if self._last_xyyaw is not None:  # the path driven, as the attempts see it (correlation "distance")
            self._path_m += float(np.hypot(*(est_xyyaw[:2] - self._last_xyyaw[:2])))
        self._last_xyyaw = est_xyyaw
        if self._fresh.stale(lmap):
            return FixAttempt(est.t, len(lmap), "stale map", 0.0, est_xyyaw=est_xyyaw)
        live = lmap.ids  # the back-end's own landmarks (those of the window are not its variables)
        if self.window is not None:  # with the landmarks the back-end dropped on the recent path
            lmap = self.window.update(lmap, est.position_m)
        rel = self._relative_covs(lmap, est)
        usable = None
        if rel is not None:  # landmarks the rover has drifted from since are not matched
            usable = np.linalg.eigvalsh(rel)[:, -1] <= (cfg.max_relative_sigmas * self._matcher_config().sigma_m) ** 2
        idx = select_local_map(lmap, est.position_m, cfg, self.min_size_m, usable)
        if idx.size < cfg.min_landmarks:
            single = self._identify(lmap, idx, est, est_xyyaw, 0.0, live)
            return single or FixAttempt(est.t, int(idx.size), "too few landmarks", 0.0, est_xyyaw=est_xyyaw)
        local_xy = lmap.xyz_world_m[idx, :2]
        t0 = time.perf_counter()
        prior = None
        sigma_pos = est.planar_sigma_m
        if cfg.prior_sigmas is not None and not is_lost(est, cfg.lost_sigma_m):  # lost: the whole catalog
            from reloc.matcher import MatchPrior
            from reloc.procrustes import Similarity2D

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
            single = self._identify(lmap, idx, est, est_xyyaw, dt, live)
            return single or FixAttempt(est.t, int(idx.size), "no match", dt, est_xyyaw=est_xyyaw)
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
        rel_fix = None
        if rel is not None:  # the inliers' drift from the rover, weighted as the fit weighs them
            w = rover_weights(L, est.position_m, cfg.fit_radius_m)
            rel_fix = np.einsum("k,kij->ij", w / w.sum(), rel[idx[pairs[:, 0]]])
        try:
            fix = fix_from_similarity(
                est, rotation, translation, scale, L, rmse, cfg, t_recv=est.t + latency, map_var_m2=map_var,
                similarity_cov=sim_cov,
                cov_scale=self._correlation_scale(est.t, pairs[:, 1]),
                relative_cov_xy=rel_fix, catalog_rows=pairs[:, 1], source=self.kinds[0],
            )
        except RelocalizerError as exc:
            return FixAttempt(est.t, int(idx.size), f"no match ({exc})", dt, est_xyyaw=est_xyyaw)
        self._note_fix(est.t, pairs[:, 1])
        return FixAttempt(est.t, int(idx.size), "fix", dt, fix, L, W, est_xyyaw, bool(getattr(result, "from_guess", False)))

    def _identify(self, lmap: LandmarkMap, idx: np.ndarray, est: PoseEstimate, est_xyyaw: np.ndarray,
                  dt_match: float, live: np.ndarray) -> FixAttempt | None:
        """A fix from two landmarks identified together (``RelocalizerConfig.pair_landmarks``),
        else a position fix from one identified alone (``single_landmark``), or None: off, or no
        landmark passes. A lost estimate is tried too: each landmark's gate holds the rover's
        drift, the false-alarm bound counts the chance entries in it, and a gate wider than the
        disc that density is counted on identifies nothing (``single_density_radius_m``).
        Landmarks anchored on a catalog entry already are left out; with ``anchor_landmarks`` the
        fix names its landmarks of ``live`` (the back-end's ids) and their entries
        (:class:`reloc.measurements.CatalogAnchor`)."""
        cfg = self.config
        idx = idx[lmap.anchored_rows[idx] < 0]  # their entry is on them: a fix would repeat it
        if not (cfg.single_landmark or cfg.pair_landmarks) or idx.size == 0:
            return None
        t0 = time.perf_counter()
        if self._single_tree is None:
            from scipy.spatial import cKDTree

            self._single_tree = cKDTree(self.catalog.xy_m)
            self._single_box = catalog_box_of(self.catalog.xy_m)
        mc = self._matcher_config()
        sigma_m = float(mc.sigma_m)
        sizes = np.asarray(self.catalog.size_m, float)
        args = (lmap, idx, est.position_m, self.catalog.xy_m, sizes, self._single_tree, cfg, sigma_m,
                mc.size_ratio_max, self._single_box)
        pair = identify_pair(*args) if cfg.pair_landmarks and idx.size >= 2 else None
        hit = None if pair is not None or not cfg.single_landmark else identify_single(*args)
        dt = dt_match + time.perf_counter() - t0
        latency = cfg.delay_s if cfg.latency == "fixed" else dt * cfg.latency_scale
        if pair is not None:
            ids, rows = np.array(pair.landmarks), np.array(pair.rows)
            l_xy, c_xy = lmap.xyz_world_m[ids, :2], self.catalog.xy_m[rows]
            rel = rover_relative_cov_xy(lmap.cov_world_m2[ids, :2, :2], np.asarray(est.cov)[:2, :2])
            sigma_c = catalog_sigma(cfg, sigma_m, sizes[rows])
            scale = self._correlation_scale(est.t, rows)
            fix = fix_from_pair(est, l_xy, rel, c_xy, cfg, sigma_c, t_recv=est.t + latency,
                                cov_scale=scale, catalog_rows=pair.rows, source=self.kinds[0],
                                anchors=self._anchors(lmap.ids[ids], rows, sizes[rows], scale, live))
            self._note_fix(est.t, rows)
            log.debug("t=%.1f s: pair %s fix, d2 %.2f / %.2f, false-alarm bound %.2e", est.t, self.kinds[0],
                      pair.d2, pair.d2_rel, pair.false_alarm)
            return FixAttempt(est.t, int(idx.size), "fix", dt, fix, l_xy, c_xy, est_xyyaw,
                              single=True, false_alarm=pair.false_alarm)
        if hit is None:
            return None
        l_xy, c_xy = lmap.xyz_world_m[hit.landmark, :2], self.catalog.xy_m[hit.row]
        sigma_c = float(catalog_sigma(cfg, sigma_m, sizes[hit.row]))
        scale = self._correlation_scale(est.t, np.array([hit.row]))
        fix = fix_from_single(est, l_xy, lmap.cov_world_m2[hit.landmark, :2, :2], c_xy, cfg, sigma_c,
                              t_recv=est.t + latency, cov_scale=scale, catalog_row=hit.row, source=self.kinds[0],
                              anchors=self._anchors(lmap.ids[[hit.landmark]], np.array([hit.row]), sizes[[hit.row]], scale, live))
        self._note_fix(est.t, np.array([hit.row]))
        log.debug("t=%.1f s: single %s fix, d2 %.2f, false-alarm bound %.2e", est.t, self.kinds[0], hit.d2,
                  hit.false_alarm)
        return FixAttempt(est.t, int(idx.size), "fix", dt, fix, l_xy[None, :], c_xy[None, :], est_xyyaw,
                          single=True, false_alarm=hit.false_alarm)

    def _anchors(self, ids: np.ndarray, rows: np.ndarray, sizes: np.ndarray, scale: float,
                 live: np.ndarray) -> tuple[CatalogAnchor, ...]:
        """The anchors of a fix identifying landmarks ``ids`` with catalog ``rows`` (their sizes
        ``sizes``): each entry at its catalog position with its own error, ``scale x
        catalog_sigma(anchor_sigma_m, size)^2``
        per axis (:func:`fgslam.match_to_fix.catalog_sigma`); none when ``anchor_landmarks`` is
        off or a landmark is not one of the back-end's (``live``)."""
        cfg = self.config
        if not cfg.anchor_landmarks or not np.isin(ids, live).all():
            return ()
        var = scale * catalog_sigma(cfg, cfg.anchor_sigma_m, sizes) ** 2
        return tuple(CatalogAnchor(self.kinds[0], int(i), int(r), self.catalog.xy_m[r], v * np.eye(2))
                     for i, r, v in zip(ids, rows, var))

    def _matcher_config(self):
        """The matcher's :class:`reloc.matcher.MatcherConfig` (its defaults for a given matcher
        that has none)."""
        mc = self._mcfg if self._mcfg is not None else getattr(self.matcher, "config", None)
        if mc is None:
            from reloc.matcher import MatcherConfig

            mc = MatcherConfig()
        return mc

    def _relative_covs(self, lmap: LandmarkMap, est: PoseEstimate) -> np.ndarray | None:
        """(N, 2, 2) the rover's planar uncertainty relative to each landmark of ``lmap``
        (:func:`fgslam.match_to_fix.rover_relative_cov_xy`); None when the rule is off
        (``max_relative_sigmas`` None), the estimate is lost or the map empty."""
        if self.config.max_relative_sigmas is None or len(lmap) == 0 or is_lost(est, self.config.lost_sigma_m):
            return None
        return rover_relative_cov_xy(lmap.cov_world_m2[:, :2, :2], np.asarray(est.cov)[:2, :2])

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
                    cat = Catalog(self.catalog.xy_m[rows], self.catalog.size_m[rows],
                                  CatalogConfig(workers=1, bin_m=self._hash_bin_m()))
                    sub = ConstellationMatcher(cat, self._mcfg)
                except RelocError as exc:  # a degenerate crop (duplicates, collinear): nothing to match
                    log.debug("catalog crop of %d rocks not usable: %s", rows.size, exc)
            hit = (rows, sub)
            self.n_crops_built += 1
        self._crops[key] = hit  # most recently used last
        while len(self._crops) > self.config.crop_cache:
            self._crops.pop(next(iter(self._crops)))
        return hit

    def _hash_bin_m(self) -> float:
        """The crops' hash bin: half the matcher's side tolerance, never below the catalog's
        default. A query walks every bin its tolerance spans on two sides: at the kilometre worlds'
        sigma (0.5 m, a 0.71 m tolerance) the default 0.08 m bin made ~18^2 runs per triangle."""
        from reloc.catalog import CatalogConfig

        return max(CatalogConfig().bin_m, 0.5 * self._matcher_config().side_tol_m)

    def _note_fix(self, t: float, catalog_rows: np.ndarray) -> None:
        self._fix_times.append(t)
        np.add.at(self._rock_uses, np.unique(catalog_rows), 1)
        self._fix_path_m = self._path_m

    def _correlation_scale(self, t: float, catalog_rows: np.ndarray) -> float:
        """Covariance multiplier of a fix at ``t`` whose inliers are catalog rocks ``catalog_rows``
        (see ``RelocalizerConfig.correlation``)."""
        cfg = self.config
        if cfg.correlation == "rocks":
            return 1.0 + float(np.mean(self._rock_uses[np.unique(catalog_rows)]))
        if cfg.correlation == "window" and cfg.correlation_window_s > 0:
            w = cfg.correlation_window_s
            return 1.0 + sum(1 for tf in self._fix_times if t - w <= tf < t)
        if cfg.correlation == "distance" and self._fix_path_m is not None:
            return distance_correlation_scale(self._path_m - self._fix_path_m, cfg.correlation_length_m)
        return 1.0

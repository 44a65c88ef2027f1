"""Constellation matcher: find where a local rock map lies in the catalog, or say it is not there.

The composer reads like the reference design (section II.B), with the fixes the issue asks for:

1. sample local triangles (each rock with pairs of its k nearest neighbours), in seeded order;
2. look each one up in the catalog's geometric hash (sides within tolerance, same handedness),
   reject candidates whose rock sizes disagree, fit a 2D similarity (Procrustes) to the three
   vertex pairs, reject scales far from 1;
3. rank every candidate pose by a coarse score (local rocks landing near a size-compatible
   catalog rock, read from a grid), group them in (heading, position) bins and verify the best
   bins: inliers under the candidate, re-fit on the inliers (Umeyama), re-score; more inliers
   win, lower RMSE breaks ties;
4. accept the best pose only if its inlier count is improbable for a wrong pose at the catalog's
   local density (Poisson-binomial tail x number of hypotheses generated, with a
   sequential-testing weight), checked after every batch, so the search stops at the first
   convincing pose.

Tracking: when the caller knows roughly where the map is (:class:`MatchPrior` with a ``guess``,
e.g. the back-end's own estimate), that pose is verified first, as one hypothesis with its own
share of the sequential test (``guess_share``); only if it does not convince does the triangle
search run (with the rest of the share, and paying for the guess's test). A localized rover then
costs one verification per attempt instead of a search, and a wrong or drifted guess costs one
verification more than the search alone.

Size: ~600 lines, above the project's ~300, for a reason: the stages already live in their own
modules (descriptors, hashing, sampling, hypotheses, scoring, procrustes, match_result); what
stays here is the search itself, whose steps (batches of hypotheses, verification of the best
bins, the sequential false-alarm test, the guess) share one per-call state (``_Search``), and the
config whose derived tolerances every step reads.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from reloc.catalog import Catalog
from reloc.config import Ge, Gt, Interval, Le, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from reloc.descriptors import label_triangles
from reloc.errors import RelocError
from reloc.hypotheses import Hypotheses, LocalTriangles, generate_hypotheses, pose_bins
from reloc.match_result import MatchResult, similarity_covariance
from reloc.procrustes import Similarity2D, umeyama_2d
from reloc.sampling import knn_triangles, neighbour_rank
from reloc.scoring import (
    CoarseScorer,
    Inliers,
    log10_binomial_tail,
    score_points,
    size_compatible_fraction,
    size_compatible_fractions,
)

__all__ = ["ConstellationMatcher", "MatchInputError", "MatchPrior", "MatchResult", "MatcherConfig"]

log = logging.getLogger(__name__)


class MatchInputError(RelocError, ValueError):
    """The local map given to the matcher is malformed (shape, NaN, non-positive sizes)."""


@dataclass(frozen=True, slots=True)
@checked(MatchInputError)
class MatcherConfig:
    """Matcher parameters (defaults in code). Lengths in metres.

    ``sigma_m``: expected per-axis position noise between local map and catalog; the side
    tolerance (``side_tol_sigmas`` x sqrt(2) x sigma; a second pass adds the candidates up to
    ``wide_side_tol_sigmas`` while fewer than ``wide_max_hypotheses`` hypotheses were generated),
    inlier radius (``inlier_sigmas`` x sigma, at least ``min_inlier_radius_m``) and vote bins
    derive from it. ``scale_tol``: allowed |scale-1|.
    ``heading_arm_m``: typical arm of a local triangle, which sets the heading error of a
    3-point pose and so the vote bins and the poses a verification reaches (rocks ~1.5 m apart;
    None: the median side of the local map's triangles, for landmarks tens of metres apart).
    ``size_ratio_max``: largest allowed ratio of matched rock diameters (None: no size check).
    ``local_neighbours``: k for local triangles. ``batch_triangles``: local triangles in the
    first batch, doubling up to ``max_batch_triangles``; ``verify_per_batch``: pose bins verified
    per batch (best coarse score first), and ``verify_by_votes`` more (most votes first, at
    least 2); ``first_stage_factor``: inlier radius multiplier of the first scoring stage (a
    3-point pose is noisier than a re-fitted one);
    ``refits``: least-squares re-fit/re-score rounds; ``polish_sigmas``: final fit on pairs
    closer than this many sigma; ``growth_reach_m``: distances from the hypothesis' triangle
    within which inliers are collected and re-fitted before the whole map is scored;
    ``density_radius_m``: radius of the local catalog-density estimate (at least 4 inlier radii);
    ``min_inliers``: fewest inliers ever accepted. ``max_log10_false_alarm``: acceptance
    threshold on log10(bound on the chance that a wrong pose is accepted), checked after every
    batch and after every verified bin (the search stops once it is met); ``early_exit_log10``:
    a stricter level for stopping in the middle of a batch (default: the acceptance threshold).
    ``metric``: both maps are metric, so the final least-squares re-fit is
    rigid (scale 1; a 3-point similarity still checks the scale of every candidate against 1
    within ``scale_tol``); False re-fits a similarity. ``seed``: order in which local triangles
    are tried, and ``fewest_candidates_first`` tries first those with the fewest expected
    hypotheses times (neighbour rank)^``rank_power`` (stable, so the seed breaks ties).
    ``max_triangles``: try at most this many local triangles (None: all).
    ``guess_share``: share of the false-alarm budget given to verifying a prior's ``guess``
    before the search (the search's stages share the rest); unused without a guess.
    """

    sigma_m: Positive = 0.1
    heading_arm_m: Positive | None = 1.5
    side_tol_sigmas: Positive = 1.0
    wide_side_tol_sigmas: Positive | None = 2.0
    wide_max_hypotheses: NonNegativeInt = 10_000
    inlier_sigmas: Positive = 2.5
    min_inlier_radius_m: NonNegative = 0.1
    scale_tol: Annotated[float, Interval(gt=0, lt=1)] = 0.02
    size_ratio_max: Annotated[float, Gt(1)] | None = 1.6
    local_neighbours: Annotated[int, Ge(2)] = 6
    batch_triangles: PositiveInt = 16
    max_batch_triangles: PositiveInt = 128
    max_triangles: PositiveInt | None = None
    verify_per_batch: PositiveInt = 8
    verify_by_votes: NonNegativeInt = 4
    first_stage_factor: Positive = 2.0
    refits: NonNegativeInt = 1
    polish_sigmas: Positive = 2.0
    growth_reach_m: tuple[float, ...] = (3.0, 6.0)
    density_radius_m: Positive = 1.5
    min_inliers: Annotated[int, Ge(3)] = 5
    max_log10_false_alarm: Annotated[float, Le(0)] = -3.0
    early_exit_log10: Annotated[float, Le(0)] = -3.0
    metric: bool = True
    fewest_candidates_first: bool = True
    rank_power: NonNegative = 3.0
    guess_share: Annotated[float, Interval(gt=0, lt=1)] = 0.25
    seed: int = 0

    def __post_init__(self) -> None:
        if any(not (math.isfinite(r) and r > 0) for r in self.growth_reach_m):
            raise MatchInputError(f"MatcherConfig.growth_reach_m must hold finite distances > 0, got {self.growth_reach_m}")

    @property
    def inlier_radius_m(self) -> float:
        return max(self.inlier_sigmas * self.sigma_m, self.min_inlier_radius_m)

    @property
    def size_log_tol(self) -> float | None:
        """Largest allowed |log| ratio of matched rock diameters (None: no size check)."""
        return None if self.size_ratio_max is None else math.log(self.size_ratio_max)

    @property
    def fit_floor_sigma_m(self) -> float:
        """Floor of the per-axis residual sigma in a fit's covariance (a fit on a few exact pairs
        is not that exact)."""
        return 0.25 * self.sigma_m

    @property
    def side_tol_m(self) -> float:
        return self.side_tol_sigmas * math.sqrt(2.0) * self.sigma_m


@dataclass(frozen=True, slots=True)
class MatchPrior:
    """Optional search restriction: the local map's centroid lies within ``radius_m`` of
    ``center_xy`` (2,) in the world frame. ``guess``: the pose (local -> world) the caller
    expects, verified before any search (tracking; see the module doc)."""

    center_xy: np.ndarray
    radius_m: float
    guess: Similarity2D | None = None


@dataclass
class _Search:
    """Mutable state of one search."""

    n_hypotheses: int = 0
    n_verified: int = 0
    poses_per_verification: float = 1.0
    poses_per_guess: float = 1.0
    n_guesses: int = 0
    stage: int = 0
    log10_weight: float = 0.0
    keys: list[np.ndarray] = field(default_factory=list)
    hyps: list[Hypotheses] = field(default_factory=list)
    coarse: list[np.ndarray] = field(default_factory=list)
    masks: np.ndarray | None = None
    verified_keys: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    verified_best: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    verified_votes: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    best: tuple[Similarity2D, Inliers] | None = None
    best_from_guess: bool = False
    size_check: tuple[np.ndarray, np.ndarray, float] | None = None
    size_fraction: float = 1.0
    done: bool = False


class ConstellationMatcher:
    """Matches local rock maps against one :class:`~reloc.catalog.Catalog`."""

    def __init__(self, catalog: Catalog, config: MatcherConfig | None = None) -> None:
        self.catalog = catalog
        self.config = config if config is not None else MatcherConfig()
        self._cat_log_size_sorted = np.sort(catalog.log_size)
        self._coarse: CoarseScorer | None = None

    @property
    def coarse_scorer(self) -> CoarseScorer:
        """The grid that ranks hypotheses (built on first use: it depends on ``sigma_m``)."""
        if self._coarse is None:
            cfg = self.config
            tol = cfg.size_log_tol
            self._coarse = CoarseScorer(
                self.catalog.xy, self.catalog.log_size, cfg.inlier_radius_m, tol
            )
        return self._coarse

    def match(
        self, local_xy: np.ndarray, local_size: np.ndarray | None = None, prior: MatchPrior | None = None
    ) -> MatchResult | None:
        """Pose of the local map (N, 2) metres, rock diameters (N,) metres, in the catalog's world
        frame, or None when no pose is convincing. Raises :class:`MatchInputError` on bad input."""
        cfg = self.config
        xy, log_size = _validate(local_xy, local_size)
        if prior is not None:
            _validate_prior(prior)
        if xy.shape[0] < 3:
            log.info("match: %d local rocks, need at least 3", xy.shape[0])
            return None
        tri = self._local_triangles(xy)
        if len(tri) == 0:
            log.info("match: no non-degenerate local triangle (collinear or duplicate rocks)")
            return None
        center = xy.mean(axis=0)
        radius = float(np.max(np.hypot(*(xy - center).T))) + cfg.inlier_radius_m
        st = _Search()
        size_log_tol = cfg.size_log_tol
        if size_log_tol is not None and log_size is not None:
            st.size_check = (log_size, self.catalog.log_size, size_log_tol)
            st.size_fraction = size_compatible_fraction(log_size, self._cat_log_size_sorted, size_log_tol)
        # vote bins as wide as a 3-point pose's error: heading from arms of ``heading_arm_m``
        # (rocks: ~1.5 m; None: the local triangles' median side), position at the centroid up
        # to the map radius away from the triangle
        arm = cfg.heading_arm_m if cfg.heading_arm_m is not None else float(np.median(tri.sides_m))
        theta_bin = float(np.clip(2.5 * cfg.side_tol_m / cfg.side_tol_sigmas / arm, 0.05, 0.5))
        xy_bin = max(0.5, 8.0 * cfg.sigma_m, theta_bin * (radius - cfg.inlier_radius_m))
        # distinct poses a verification can reach: its vote bin (about a 3-point pose's error) at
        # the resolution of the inlier radius (r in position, r at the map's edge in heading)
        r = cfg.inlier_radius_m
        reach_theta, reach_xy = max(1.0, theta_bin * (radius - r) / r), max(1.0, xy_bin / r)
        st.poses_per_verification = reach_theta * reach_xy**2
        # a guess is verified from one pose: its first stage reaches first_stage_factor inlier
        # radii each way (position, and heading at the map's edge), not a whole vote bin
        st.poses_per_guess = min(st.poses_per_verification, (2.0 * cfg.first_stage_factor) ** 3)
        guess = None if prior is None else prior.guess
        if guess is not None:
            self._verify_guess(xy, guess, st)
        if not st.done:  # the triangle search, with what the guess left of the test
            share = 1.0 if guess is None else 1.0 - cfg.guess_share
            self._search(xy, log_size, tri, center, (theta_bin, xy_bin), prior, share, st)
        if st.best is None:
            return None
        st.best = self._settle(xy, *st.best, st)
        lfa, p = self._log10_fa(st, xy)
        sim, inl = st.best
        log.debug("match: best %d inliers, log10 FA %.1f, %d hypotheses", inl.count, lfa, st.n_hypotheses)
        if lfa > cfg.max_log10_false_alarm or inl.count < cfg.min_inliers:
            return None
        cov4 = similarity_covariance(
            sim,
            xy[inl.local_idx],
            self.catalog.xy[inl.catalog_idx],
            floor_sigma_m=cfg.fit_floor_sigma_m,
            with_scale=not cfg.metric,
        )
        return MatchResult(
            rotation_rad=float(sim.theta_rad),
            translation=np.asarray(sim.translation, float),
            scale=float(sim.scale),
            inlier_pairs=np.stack([inl.local_idx, inl.catalog_idx], axis=1).astype(np.int64),
            rmse_m=inl.rmse_m,
            n_local=int(xy.shape[0]),
            from_guess=st.best_from_guess,
            n_hypotheses=st.n_hypotheses,
            n_verified=st.n_verified,
            chance_probability=p,
            log10_false_alarm=lfa,
            similarity_cov=cov4,
        )

    # -- stages -------------------------------------------------------------------------------
    def _search(
        self, xy: np.ndarray, log_size: np.ndarray | None, tri: LocalTriangles, center: np.ndarray,
        bins: tuple[float, float], prior: MatchPrior | None, share: float, st: _Search,
    ) -> None:
        """The triangle search (steps 1-4 of the module doc) with ``share`` of the false-alarm
        budget, into ``st``; stops at the first convincing pose."""
        cfg = self.config
        theta_bin, xy_bin = bins
        size_log_tol = cfg.size_log_tol
        order = self._triangle_order(xy, tri, log_size)
        if cfg.max_triangles is not None:
            order = order[: cfg.max_triangles]
        coarse = self.coarse_scorer
        st.masks = coarse.masks(log_size, xy.shape[0])
        # stages: batches of triangles at the side tolerance, then (``wide_side_tol_sigmas``) the
        # same triangles again for the candidates between that and the wider tolerance
        passes = [(cfg.side_tol_m, None)]
        if cfg.wide_side_tol_sigmas is not None and cfg.wide_side_tol_sigmas > cfg.side_tol_sigmas:
            passes.append((cfg.wide_side_tol_sigmas * math.sqrt(2.0) * cfg.sigma_m, cfg.side_tol_m))
        stages = []
        size = cfg.batch_triangles
        for tol_m, inner_m in passes:
            start = 0
            while start < order.size:
                stages.append((order[start : start + size], tol_m, inner_m))
                start, size = start + size, min(2 * size, cfg.max_batch_triangles)
        weights = [w * share for w in _stage_weights([sum(1 for s_ in stages if s_[2] is inner) for _, inner in passes])]
        for s_idx, (sel, tol_m, inner_m) in enumerate(stages):
            if inner_m is not None and st.n_hypotheses >= cfg.wide_max_hypotheses:
                break  # the wider pass only while the search is still cheap
            batch = tri.take(sel)
            st.stage += 1
            st.log10_weight = math.log10(weights[s_idx])
            h = generate_hypotheses(
                self.catalog, xy, log_size, batch,
                side_tol_m=tol_m, scale_tol=cfg.scale_tol,
                size_log_tol=size_log_tol, inner_tol_m=inner_m,
            )
            if prior is not None and len(h):
                h = _apply_prior(h, center, prior)
            st.n_hypotheses += len(h)
            if len(h):
                st.keys.append(pose_bins(h, center, theta_bin, xy_bin))
                st.hyps.append(h)
                st.coarse.append(coarse.score(h.theta_rad, h.scale, h.translation, xy, st.masks))
                self._verify_top(xy, center, st)
            # sequential acceptance: stop as soon as the best pose is convincing at this stage
            if st.done or (
                st.best is not None
                and st.best[1].count >= cfg.min_inliers
                and self._log10_fa(st, xy)[0] <= cfg.max_log10_false_alarm
            ):
                break

    def _local_triangles(self, xy: np.ndarray) -> LocalTriangles:
        cc = self.catalog.config
        tri = knn_triangles(xy, self.config.local_neighbours)
        lab = label_triangles(xy, tri, min_side_m=cc.min_side_m, min_shape=cc.min_shape)
        k = lab.keep
        return LocalTriangles(lab.vertices[k].astype(np.int64), lab.sides_m[k], lab.handedness[k])

    def _triangle_order(
        self, xy: np.ndarray, tri: LocalTriangles, log_size: np.ndarray | None
    ) -> np.ndarray:
        """Order in which local triangles are tried: seeded random, then
        (``fewest_candidates_first``) stably by their expected number of hypotheses (catalog
        triangles of that shape, from the hash's coarse histogram, times the fraction of catalog
        rocks size-compatible with each vertex) times (neighbour rank)^``rank_power``. Whether
        a local triangle is also in the catalog hardly depends on the first factor, which spans
        three orders of magnitude, so distinctive triangles find the true pose with far fewer
        hypotheses (fewer to generate, score and pay for in the acceptance test). The order uses
        the local map and the catalog's shape and size statistics only, never a pose's inliers."""
        cfg = self.config
        order = np.random.default_rng(cfg.seed).permutation(len(tri))
        if not cfg.fewest_candidates_first:
            return order
        tri = tri.take(order)
        tol = cfg.side_tol_m + cfg.scale_tol * tri.sides_m[:, 2]
        n = self.catalog.hash.estimate_count(tri.sides_m, tri.handedness, tol)
        if log_size is not None and cfg.size_ratio_max is not None:
            # expected survivors of the size check: rocks of unusual size are distinctive too
            frac = size_compatible_fractions(log_size, self._cat_log_size_sorted, cfg.size_log_tol)
            n *= np.prod(frac[tri.vertices], axis=1)
        # triangles of farther neighbours are less often in the catalog's index (measured at
        # 100 000 clustered rocks: 18 % of rank-2 local triangles have a true match, 4 % of
        # rank-6 ones); the steep weight also tries the compact triangles first
        n *= neighbour_rank(xy, tri.vertices, cfg.local_neighbours).astype(float) ** cfg.rank_power
        return order[np.argsort(n, kind="stable")]

    def _verify_top(self, xy: np.ndarray, center: np.ndarray, st: _Search) -> None:
        """Verify the best hypotheses (two-stage scoring, see module doc). Every hypothesis has a
        coarse score (local rocks near a size-compatible catalog rock, from the grid); hypotheses
        are grouped in pose bins, and the bins with the best coarse score are verified at their
        best-scored member. A bin is verified again only when a member with a
        better coarse score arrives."""
        cfg = self.config
        if len(st.hyps) > 1:
            st.hyps[:] = [_concat(st.hyps)]
            st.keys[:] = [np.concatenate(st.keys)]
            st.coarse[:] = [np.concatenate(st.coarse)]
        hyp_all, keys, score = st.hyps[0], st.keys[0], st.coarse[0]
        # sort by (bin, -score, -span): the first hypothesis of each bin is its best
        order = np.lexsort((-hyp_all.span_m, -score, keys))
        uniq, first, votes = np.unique(keys[order], return_index=True, return_counts=True)
        best = score[order[first]]
        seen = np.full(uniq.size, -1, np.int64)
        seen_votes = np.zeros(uniq.size, np.int64)
        if st.verified_keys.size:
            at = np.minimum(np.searchsorted(st.verified_keys, uniq), st.verified_keys.size - 1)
            hit = st.verified_keys[at] == uniq
            seen[hit] = st.verified_best[at[hit]]
            seen_votes[hit] = st.verified_votes[at[hit]]
        # best coarse score first; ties by bin key (deterministic)
        cand = np.flatnonzero(best > seen)
        cand = cand[np.argsort(-best[cand], kind="stable")][: cfg.verify_per_batch]
        # and the bins most voted for by different triangles: far from its triangle a 3-point
        # pose is poor, so when few local rocks are in the catalog, the coarse score of the true
        # pose can trail chance scores, while its votes stand out
        by_votes = np.flatnonzero((votes >= 2) & (votes > seen_votes))
        by_votes = by_votes[np.argsort(-votes[by_votes], kind="stable")][: cfg.verify_by_votes]
        by_votes = by_votes[~np.isin(by_votes, cand)]
        cand = np.concatenate([cand, by_votes])
        if cand.size == 0:
            return
        # the coarse score and votes each bin was verified at (sorted keys, for searchsorted)
        vk = np.concatenate([st.verified_keys, uniq[cand]])
        vb = np.concatenate([st.verified_best, best[cand]])
        vv = np.concatenate([st.verified_votes, votes[cand]])
        vk, first_at = np.unique(vk[::-1], return_index=True)  # the newest entry of each key
        st.verified_keys = vk
        st.verified_best, st.verified_votes = vb[::-1][first_at], vv[::-1][first_at]
        for b in cand:
            i = int(order[first[b]])
            sim = Similarity2D(float(hyp_all.theta_rad[i]), hyp_all.translation[i], float(hyp_all.scale[i]))
            st.n_verified += 1
            found = self._verify_one(xy, sim, xy[hyp_all.local_vertices[i]].mean(axis=0), st)
            if found is None:
                continue
            sim, inl = found
            if st.best is None or (inl.count, -inl.rmse_m) > (st.best[1].count, -st.best[1].rmse_m):
                st.best, st.best_from_guess = (sim, inl), False
                # a convincing pose ends the search at once: the test at this stage's weight
                # and hypothesis count does not depend on how many bins were verified before
                stop = min(cfg.early_exit_log10, cfg.max_log10_false_alarm)
                if inl.count >= cfg.min_inliers and self._log10_fa(st, xy)[0] <= stop:
                    st.done = True
                    return

    def _verify_guess(self, xy: np.ndarray, guess: Similarity2D, st: _Search) -> None:
        """Verify the prior's guess as the first stage (one hypothesis, one verification, the
        ``guess_share`` of the test); ends the search when it convinces. No guided growth: the
        guess is as good over the whole map as at any point of it, and growing from one anchor
        ties the fit to that part of the map (my2020, fixes' p90 error 0.090 m with growth from
        the centroid, 0.082 without; the triangle search: 0.084)."""
        cfg = self.config
        st.stage += 1
        st.log10_weight = math.log10(cfg.guess_share)
        st.n_hypotheses += 1
        st.n_verified += 1
        st.n_guesses += 1
        found = self._verify_one(xy, guess, None, st)
        if found is None:
            return
        st.best, st.best_from_guess = found, True
        if found[1].count >= cfg.min_inliers and self._log10_fa(st, xy)[0] <= cfg.max_log10_false_alarm:
            st.done = True

    def _score(self, sim: Similarity2D, xy: np.ndarray, sel: np.ndarray | None, radius_m: float, st: _Search) -> Inliers:
        """Inliers of local rocks ``sel`` (all when None) under ``sim``, indices into ``xy``."""
        if sel is None:
            return score_points(self.catalog.tree, sim.apply(xy), radius_m, st.size_check)
        chk = None if st.size_check is None else (st.size_check[0][sel], st.size_check[1], st.size_check[2])
        inl = score_points(self.catalog.tree, sim.apply(xy[sel]), radius_m, chk)
        return Inliers(sel[inl.local_idx], inl.catalog_idx, inl.dist_m)

    def _fit(self, xy: np.ndarray, inl: Inliers) -> Similarity2D:
        return umeyama_2d(xy[inl.local_idx], self.catalog.xy[inl.catalog_idx], with_scale=not self.config.metric)

    def _verify_one(
        self, xy: np.ndarray, sim: Similarity2D, anchor_xy: np.ndarray | None, st: _Search
    ) -> tuple[Similarity2D, Inliers] | None:
        """Two-stage scoring of one hypothesis (guided growth around ``anchor_xy``, skipped when
        None; first stage, re-fits, polish); returns the re-fitted pose and its inliers, or None."""
        cfg = self.config
        r = cfg.inlier_radius_m
        # guided growth: a 3-point pose is accurate near its triangle only, so first collect
        # inliers close to it, re-fit, and widen the reach
        if anchor_xy is not None:
            reach = np.hypot(*(xy - anchor_xy).T)
            for reach_m in cfg.growth_reach_m:
                inl = self._score(sim, xy, np.flatnonzero(reach <= reach_m), cfg.first_stage_factor * r, st)
                if inl.count >= 3:
                    sim = self._fit(xy, inl)
        # first stage with a wider radius: the pose is still noisier than the final one
        inl = self._score(sim, xy, None, cfg.first_stage_factor * r, st)
        if inl.count < max(3, cfg.min_inliers - 1):
            return None
        # second stage: least-squares re-fit on the inliers, re-score (repeated ``refits`` times)
        # (the returned inliers are always scored at the final radius ``r``)
        for _ in range(max(cfg.refits, 1)):
            sim = self._fit(xy, inl)
            inl = self._score(sim, xy, None, r, st)
            if inl.count < 3:
                return None
        # polish on the closest pairs: a wrongly paired neighbour sits near the radius and
        # drags the heading; the fit on pairs within ``polish_sigmas`` sigma is robust to it
        close = inl.dist_m <= cfg.polish_sigmas * cfg.sigma_m
        if np.count_nonzero(close) >= max(cfg.min_inliers, 3):
            pol = self._fit(xy, Inliers(inl.local_idx[close], inl.catalog_idx[close], inl.dist_m[close]))
            pol_inl = self._score(pol, xy, None, r, st)
            if pol_inl.count >= 3:
                sim, inl = pol, pol_inl
        if abs(sim.scale - 1.0) > cfg.scale_tol + cfg.sigma_m / 2.0:
            return None
        return sim, inl

    def _settle(
        self, xy: np.ndarray, sim: Similarity2D, inl: Inliers, st: _Search, rounds: int = 4
    ) -> tuple[Similarity2D, Inliers]:
        """Re-fit the winning pose on its inliers until they stop improving (more inliers, or as
        many with a lower RMSE): an early stop can leave a pose whose last re-fit still moved it."""
        for _ in range(rounds):
            new_sim = self._fit(xy, inl)
            new_inl = self._score(new_sim, xy, None, self.config.inlier_radius_m, st)
            if (new_inl.count, -new_inl.rmse_m) <= (inl.count, -inl.rmse_m):
                break
            sim, inl = new_sim, new_inl
        return sim, inl

    def _chance(self, sim: Similarity2D, xy: np.ndarray, st: _Search) -> np.ndarray:
        """Chance (M,) that each local rock, placed by ``sim``, lands on a size-compatible catalog rock.

        The catalog density is measured around every transformed local rock (radius
        ``density_radius_m``, at least 4 inlier radii), so clustered catalogs are not credited
        with the sparse areas between clusters. Rocks a local rock matched are counted too (a
        conservative choice: leaving them out makes an inlier in a sparse area look impossible
        by chance), and two pseudo-rocks at the catalog's mean density regularise small counts.
        ``f``, the fraction of catalog rocks with a size compatible with the local rocks', is
        their mean (per-rock fractions would lower the mean chance: not conservative).
        """
        cfg = self.config
        r = cfg.inlier_radius_m
        rd = max(cfg.density_radius_m, 4.0 * r)
        pts = sim.apply(xy)
        tree = self.catalog.tree
        disc = tree.query_ball_point(pts, r=rd, return_length=True)
        pseudo = 2.0
        rho = (disc + pseudo) / (math.pi * rd * rd + pseudo / self.catalog.density_per_m2)
        return -np.expm1(-rho * st.size_fraction * math.pi * r * r)

    def _log10_fa(self, st: _Search, xy: np.ndarray) -> tuple[float, float]:
        """(log10 bound on the chance that a wrong pose is accepted, mean chance probability).

        Under a wrong pose the inlier count beyond the 3 rocks of the generating triangle is
        bounded by Binomial(M - 3, mean p_i) (Hoeffding), Bonferroni over the poses tested so far
        (every hypothesis generated, plus ``poses_per_verification`` for every verified bin and
        ``poses_per_guess`` for a verified guess: its re-fits move the pose across its 3-point
        uncertainty, or a guess's across its first-stage radius, and keep the best), and the
        sequential-testing weight of the current stage (:func:`_stage_weights`). A guess's
        inliers are all evidence (it was not built from three of them).
        """
        sim, inl = st.best
        p = float(np.mean(self._chance(sim, xy, st)))
        # the 3 rocks of the generating triangle are inliers by construction (whichever rocks
        # end up as inliers after the re-fits, 3 of them are not evidence); a guess was not
        # built from the map's rocks, so every inlier of its pose is evidence
        free = 0 if st.best_from_guess else 3
        tail = log10_binomial_tail(inl.count - free, xy.shape[0] - free, p)
        log10_weight = st.log10_weight
        n_tests = (st.n_hypotheses + (st.n_verified - st.n_guesses) * st.poses_per_verification
                   + st.n_guesses * st.poses_per_guess)
        lfa = tail + math.log10(max(n_tests, 1.0)) - log10_weight
        return lfa, p


def _stage_weights(n_stages: list[int]) -> list[float]:
    """Sequential-testing weight of every stage, given the number of stages of each pass; the
    weights sum to 1, so stopping at the first stage whose best pose passes at its weight does
    not raise the false-alarm bound. A pass with share c gives its stage s < S weight c 2^-(s+1)
    and its last stage the rest (one pass: 1/4, 1/8, ..., last >= 1/2). The first pass has the
    share 3/4 when a wider second pass follows (which has 1/4)."""
    rest = len(n_stages) - 1
    shares = [1.0] if rest == 0 else [0.75] + [0.25 / rest] * rest
    out = []
    for share, n in zip(shares, n_stages):
        if n == 1:
            out.append(share)
            continue
        first = [share * 2.0 ** -(s + 1) for s in range(1, n)]  # 1/4, 1/8, ... of the share
        out += first + [share - sum(first)]
    return out


def _validate(local_xy: np.ndarray, local_size: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    xy = np.asarray(local_xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise MatchInputError(f"local_xy must have shape (N, 2), got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise MatchInputError("local_xy contains NaN or infinite values")
    if local_size is None:
        return xy, None
    size = np.asarray(local_size, dtype=float)
    if size.shape != (xy.shape[0],):
        raise MatchInputError(f"local_size must have shape ({xy.shape[0]},), got {size.shape}")
    if not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise MatchInputError("local_size must be finite and positive (rock diameters in metres)")
    return xy, np.log(size).astype(np.float32)


def _validate_prior(prior: MatchPrior) -> None:
    c = np.asarray(prior.center_xy, dtype=float)
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise MatchInputError(f"prior center_xy must be 2 finite values, got {prior.center_xy!r}")
    if not (math.isfinite(prior.radius_m) and prior.radius_m > 0):
        raise MatchInputError(f"prior radius_m must be finite and > 0, got {prior.radius_m}")
    g = prior.guess
    if g is not None and not (
        math.isfinite(g.theta_rad) and math.isfinite(g.scale) and g.scale > 0
        and np.asarray(g.translation).shape == (2,) and np.all(np.isfinite(g.translation))
    ):
        raise MatchInputError(f"prior guess must be a finite similarity with scale > 0, got {g!r}")


def _apply_prior(h: Hypotheses, center: np.ndarray, prior: MatchPrior) -> Hypotheses:
    c, s = np.cos(h.theta_rad), np.sin(h.theta_rad)
    cx = h.scale * (c * center[0] - s * center[1]) + h.translation[:, 0]
    cy = h.scale * (s * center[0] + c * center[1]) + h.translation[:, 1]
    pc = np.asarray(prior.center_xy, float)
    ok = np.hypot(cx - pc[0], cy - pc[1]) <= prior.radius_m
    return Hypotheses(
        h.theta_rad[ok], h.scale[ok], h.translation[ok], h.local_vertices[ok], h.catalog_vertices[ok], h.span_m[ok]
    )


def _concat(hs: list[Hypotheses]) -> Hypotheses:
    return Hypotheses(
        np.concatenate([h.theta_rad for h in hs]),
        np.concatenate([h.scale for h in hs]),
        np.concatenate([h.translation for h in hs]),
        np.concatenate([h.local_vertices for h in hs]),
        np.concatenate([h.catalog_vertices for h in hs]),
        np.concatenate([h.span_m for h in hs]),
    )


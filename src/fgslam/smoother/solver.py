"""The iSAM2 solver behind the smoother: full-history ISAM2 or IncrementalFixedLagSmoother, with
input validation and a way back after a failed update.

GTSAM leaves an ISAM2 unusable when an update throws (e.g. "Indeterminant linear system"), so:
inputs are validated first (finite values, every key known); risky updates (fixes, retractions)
can be preceded by :meth:`Solver.snapshot` (a copy of the ISAM2, full mode); and any failure is
recovered by rebuilding the solver from its own factor graph and linearization point without the
failed batch (and switching Cholesky -> QR when the failure was an indeterminant system).
Variables are read by their key symbol's type (:func:`fgslam.smoother.kinds.variable_type`:
poses, the calibration, and each landmark kind's own); a key of no known symbol is an error.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import gtsam
import numpy as np

from fgslam.errors import SmootherError
from fgslam.smoother.config import Factorization, SmootherConfig
from fgslam.smoother.covariance import tree_marginals
from fgslam.smoother.kinds import (
    CALIB_SYMBOL,
    OFFSET_SYMBOL,
    POSE_SYMBOL,
    SLIP_SYMBOL,
    YAW_BIAS_SYMBOL,
    symbol_of,
    variable_type,
)
from reloc.kinds import kinds_with

log = logging.getLogger(__name__)


class SolverUpdateError(SmootherError):
    """An iSAM2 update failed; the solver was restored and the batch dropped."""


def _params(cfg: SmootherConfig, factorization: Factorization) -> gtsam.ISAM2Params:
    p = gtsam.ISAM2Params()
    r = cfg.relinearize_threshold
    fixed_lag = cfg.fixed_lag_s > 0.0
    if r == 0.0 or (fixed_lag and cfg.fixed_lag_translation_threshold_m == 0.0) or (
            not fixed_lag and cfg.landmark_relinearize_scale == 1.0):
        p.setRelinearizeThreshold(r)
    else:  # per variable type: poses X (6,), every kind's landmarks, the calibration C (4,)
        # fixed-lag: a pose's translation and a landmark relinearize beyond
        # fixed_lag_translation_threshold_m (a fix moves the whole window by decimetres, which
        # relinearized nearly every variable at once and sent iSAM2 to a batch step); full mode:
        # landmarks at landmark_relinearize_scale times the pose threshold
        tr = cfg.fixed_lag_translation_threshold_m if fixed_lag else r
        lm = cfg.fixed_lag_translation_threshold_m if fixed_lag else r * cfg.landmark_relinearize_scale
        th = gtsam.ISAM2ThresholdMap()
        th.insert((POSE_SYMBOL, np.array([r, r, r, tr, tr, tr])))  # Pose3 tangent: rotation, then translation
        for kind in kinds_with("smoother"):
            dim = kind.layer("smoother").variable.dim
            th.insert((kind.symbol, np.full(dim, lm)))
        th.insert((CALIB_SYMBOL, np.full(4, r)))  # the stereo calibration, if any
        th.insert((SLIP_SYMBOL, np.full(1, 0.1 * r)))  # the slip, if estimated
        th.insert((YAW_BIAS_SYMBOL, np.full(1, 1e-7)))  # the yaw-rate bias (rad/s), if estimated
        th.insert((OFFSET_SYMBOL, np.array([tr, tr, r])))  # the fix sources' offsets (m, m, rad), if any
        p.setRelinearizeThreshold(th)
    p.relinearizeSkip = cfg.relinearize_skip
    p.setFactorization("QR" if factorization is Factorization.QR else "CHOLESKY")
    p.enablePartialRelinearizationCheck = cfg.partial_relinearization_check
    p.findUnusedFactorSlots = False  # new factor indices are then predictable and stable
    return p


def _value(values: gtsam.Values, key: int):
    """The value of ``key`` as its symbol's variable type reads it."""
    return variable_type(symbol_of(key)).value(values, key)


def _value_finite(values: gtsam.Values, key: int) -> bool:
    vt = variable_type(symbol_of(key))
    return bool(np.all(np.isfinite(vt.as_array(vt.value(values, key)))))


class Solver:
    """One incremental solver; ``fixed_lag_s`` > 0 selects the fixed-lag smoother."""

    def __init__(self, cfg: SmootherConfig) -> None:
        self.cfg = cfg
        self.factorization = cfg.factorization
        self.fixed_lag = cfg.fixed_lag_s > 0.0
        self._alive: set[int] = set()
        self._new_solver()
        self.n_recoveries = 0
        self.n_qr_retries = 0  # batches that failed in Cholesky and went in with QR
        self.n_updates = 0
        self.n_cholesky_returns = 0
        self.n_compactions = 0  # rebuilds that dropped the removed factors' slots (compact_after_slots)
        self._compact_at = cfg.compact_after_slots  # slots at which the next compaction is due
        self._qr_until: int | None = None  # after a Cholesky failure: QR until this many updates
        self._qr_spell = cfg.cholesky_retry_updates
        # told old -> new factor indices whenever the solver is rebuilt (fix records hold indices)
        self.on_rebuild: Callable[[dict[int, int]], None] | None = None
        self._maps_since_snapshot: list[dict[int, int]] | None = None  # rebuilds since snapshot()

    def _new_solver(self) -> None:
        params = _params(self.cfg, self.factorization)
        if self.fixed_lag:
            self.ifls = gtsam.IncrementalFixedLagSmoother(self.cfg.fixed_lag_s, params)
            self.isam = None
        else:
            self.isam = gtsam.ISAM2(params)
            self.ifls = None

    # ------------------------------------------------------------------ queries
    def alive(self, key: int) -> bool:
        """Whether ``key`` is a variable of the solver (not yet marginalized)."""
        return key in self._alive

    def pose(self, key: int) -> np.ndarray:
        """Current estimate of Pose3 ``key`` as (4, 4)."""
        s = self.ifls if self.fixed_lag else self.isam
        return s.calculateEstimatePose3(key).matrix()

    def point(self, key: int) -> np.ndarray:
        """Current estimate of Point3 ``key`` (3,)."""
        s = self.ifls if self.fixed_lag else self.isam
        return np.asarray(s.calculateEstimatePoint3(key), dtype=float)

    def estimate(self, key: int) -> np.ndarray:
        """Current estimate of any variable ``key``, as an array (its symbol's variable type)."""
        vt = variable_type(symbol_of(key))
        return vt.as_array(vt.estimate(self.ifls if self.fixed_lag else self.isam, key))

    def marginal_cov(self, key: int) -> np.ndarray:
        """Marginal covariance of ``key`` (GTSAM tangent, body frame for poses)."""
        s = self.ifls if self.fixed_lag else self.isam
        return np.asarray(s.marginalCovariance(key), dtype=float)

    def marginal_covs(self, keys: list[int]) -> list[np.ndarray]:
        """Marginal covariances of many ``keys`` at once (GTSAM tangent, body frame for poses).

        One batch factorization of the current graph at the current estimate, then one
        top-down pass over its Bayes tree (:func:`fgslam.smoother.covariance.tree_marginals`):
        asking iSAM2's Bayes tree key by key costs up to a second per key on a large map (my2020:
        ~900 keyframes took minutes), ``gtsam.Marginals`` (one shortcut per key) ~50 s there.
        Falls back to the key-by-key path if the batch system is singular."""
        if not keys:
            return []
        src = self.factors()
        graph = gtsam.NonlinearFactorGraph()
        for i in range(src.size()):
            if src.exists(i):
                graph.add(src.at(i))
        s = self.ifls if self.fixed_lag else self.isam
        try:
            bayes_tree = graph.linearize(s.calculateEstimate()).eliminateMultifrontal()
            covs = tree_marginals(bayes_tree, _tangent_dim, set(keys))
            return [covs[k] for k in keys]
        except (RuntimeError, KeyError) as exc:  # indeterminant or ill-posed batch system
            log.warning("batch marginals failed (%s); computing them key by key", exc)
            return [self.marginal_cov(k) for k in keys]

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """The solver's current nonlinear factor graph (removed slots are null)."""
        return self.ifls.getFactors() if self.fixed_lag else self.isam.getFactorsUnsafe()

    def theta(self) -> gtsam.Values:
        """The linearization point."""
        return self.ifls.getLinearizationPoint() if self.fixed_lag else self.isam.getLinearizationPoint()

    # ------------------------------------------------------------------ update
    def validate(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, remove: list[int]) -> None:
        """Raise SolverUpdateError if a new value is not finite, a key is unknown, or a value is
        already in the solver."""
        new_keys = set(values.keys())
        for k in new_keys:
            if k in self._alive:
                raise SolverUpdateError(f"value {gtsam.DefaultKeyFormatter(k)} is already in the solver")
            if not _value_finite(values, k):
                raise SolverUpdateError(f"value {gtsam.DefaultKeyFormatter(k)} is not finite")
        for i in range(graph.size()):
            f = graph.at(i)
            for k in f.keys():  # noqa: SIM118 (a gtsam factor is not iterable)
                if k not in new_keys and k not in self._alive:
                    raise SolverUpdateError(
                        f"factor {i} uses key {gtsam.DefaultKeyFormatter(k)} that is not in the solver"
                    )
        n = self.factors().size()
        bad = [i for i in remove if i < 0 or i >= n]
        if bad:
            raise SolverUpdateError(f"factor indices {bad} to remove do not exist")

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        timestamps: dict[int, float] | None = None,
        remove: list[int] | None = None,
        last_keys: tuple[int, ...] = (),
    ) -> list[int]:
        """One iSAM2 update; returns the indices of the new factors. Raises SolverUpdateError after
        restoring the solver when the update fails (the batch is then not applied).

        ``last_keys`` (full mode) are eliminated last (in any order among them), so that they
        form a small root clique of the Bayes tree: a marginal of one of them is then read from
        the root instead of computed through a shortcut (5-40 ms; after a late fix iSAM2 would
        otherwise put the fix's old keyframe last). The newest keyframe alone at the end made a
        root clique of it and the rocks around it (my2020: 12 ms a marginal after a fix); with the
        previous keyframe, a root of the two poses (1.8 ms). The fixed-lag smoother orders keys
        by time itself (newest last)."""
        remove = list(remove or [])
        self.validate(graph, values, remove)
        if values.size() > 0:  # a keyframe (not a fix, which may be restored from a snapshot)
            self._maybe_back_to_cholesky()
        self.n_updates += 1
        n_before = self.factors().size()
        try:
            idx = self._apply(graph, values, timestamps, remove, last_keys)
        except (RuntimeError, ValueError) as exc:  # gtsam raises ValueError from its ordering
            was_cholesky = self.factorization is Factorization.CHOLESKY
            self._recover(n_before, graph.size(), set(values.keys()), str(exc))
            if not (was_cholesky and self.factorization is Factorization.QR and not remove):
                raise SolverUpdateError(f"iSAM2 update failed and was rolled back: {exc}") from exc
            # Cholesky's "indeterminate" is a heuristic (consecutive pivots 2^12 apart), which a
            # well-posed system trips where metres of absolute uncertainty meet millimetres of
            # odometry: the same batch again, in QR, before anything of it is given up
            n_before = self.factors().size()
            try:
                idx = self._apply(graph, values, timestamps, remove, last_keys)
            except (RuntimeError, ValueError) as exc2:
                self._recover(n_before, graph.size(), set(values.keys()), str(exc2), qr_retry=True)
                raise SolverUpdateError(f"iSAM2 update failed, in QR as well, and was rolled back: {exc2}") from exc2
            self.n_qr_retries += 1
            log.warning("the failed batch went in with QR (%d factors)", graph.size())
        self._alive |= set(values.keys())
        if self.fixed_lag:
            self._alive = set(self.ifls.timestamps().keys())
            if values.size() > 0:
                self._maybe_compact()
        return idx

    def _maybe_compact(self) -> None:
        """Rebuild the fixed-lag solver from its live factors once its slots (live, removed and
        marginalized factors: GTSAM never reuses one) reach ``compact_after_slots`` and 2 x the
        live factors; a rebuild that fails leaves the solver as it was until as many slots again."""
        every = self.cfg.compact_after_slots
        g = self.factors()
        if every <= 0 or g.size() < max(self._compact_at, 2 * g.nrFactors()):
            return
        try:
            n = self._rebuild(g.size(), set())
        except (RuntimeError, ValueError) as exc:
            first = next((ln for ln in str(exc).splitlines() if ln.strip()), str(exc))
            log.warning("compacting the smoother's %d factor slots failed (%s); kept as it was", g.size(), first)
            self._compact_at = g.size() + every
            return
        self.n_compactions += 1
        self._compact_at = every
        log.debug("smoother compacted: %d factor slots -> %d", g.size(), n)

    def _apply(self, graph, values, timestamps, remove, last_keys) -> list[int]:
        """One update of the current solver; the indices of the new factors."""
        if self.fixed_lag:
            self.ifls.update(graph, values, dict(timestamps or {}), remove)
            return list(self.ifls.getISAM2Result().getNewFactorsIndices())
        res = self.isam.update(graph, values, self._update_params(remove, last_keys))
        return list(res.getNewFactorsIndices())

    @staticmethod
    def _update_params(remove: list[int], last_keys: tuple[int, ...]) -> gtsam.ISAM2UpdateParams:
        p = gtsam.ISAM2UpdateParams()
        p.removeFactorIndices = remove
        if last_keys:
            # CCOLAMD groups must be contiguous from 0: everything else stays in group 0, and the
            # keys share group 1 (iSAM2 drops the keys it does not re-eliminate from the
            # constraint, so a group 2 could be left without a group 1: "given ordering contains
            # variables that are not involved in the factor graph")
            groups = gtsam.KeyGroupMap()
            for key in last_keys:
                groups.insert2(key, 1)
            p.constrainedKeys = groups
        return p

    def extra_iterations(self, n: int, last_keys: tuple[int, ...] = ()) -> None:
        """Run ``n`` empty updates: iSAM2 takes one Gauss-Newton step per update."""
        for _ in range(n):
            if self.fixed_lag:
                self.ifls.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, [])
            else:
                self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(),
                                 self._update_params([], last_keys))

    # ------------------------------------------------------------------ way back
    def snapshot(self) -> gtsam.ISAM2 | None:
        """A copy of the full-mode ISAM2 (None in fixed-lag mode, which recovers by rebuilding)."""
        self._maps_since_snapshot = []
        return None if self.fixed_lag else gtsam.ISAM2(self.isam)

    def restore(self, snap: gtsam.ISAM2 | None, alive: set[int]) -> None:
        """Go back to ``snap`` taken by :meth:`snapshot`, with the key set at that time (and the
        factor indices of then: ``on_rebuild`` is told the way back from any rebuild since)."""
        if snap is not None:
            self.isam = snap
            self._alive = set(alive)
            back: dict[int, int] = {}
            for m in self._maps_since_snapshot or []:  # compose snapshot -> now ...
                back = {k: m[v] for k, v in back.items() if v in m} if back else dict(m)
            if back and self.on_rebuild is not None:  # ... and invert it
                self.on_rebuild({new: old for old, new in back.items()})
        self._maps_since_snapshot = None

    def _recover(self, n_before: int, n_new: int, new_keys: set[int], message: str, qr_retry: bool = False) -> None:
        """Rebuild the solver from its graph and linearization point without the failed batch
        (``qr_retry``: the batch failed in QR just after failing in Cholesky: the batch is at
        fault, not the factorization, whose QR spell stays as it is)."""
        self.n_recoveries += 1
        first = next((ln for ln in message.splitlines() if ln.strip()), message)
        if "ndetermin" in message and not qr_retry:  # 4.3 spells it "Indeterminate"
            if self.factorization is Factorization.CHOLESKY:
                log.warning("Cholesky failed (%s); switching the smoother to QR for %d updates", first, self._qr_spell)
                self.factorization = Factorization.QR
            else:  # QR failed as well, or Cholesky failed again soon after its return: a longer spell
                self._qr_spell *= 2
            if self.cfg.factorization is Factorization.CHOLESKY:
                self._qr_until = self.n_updates + self._qr_spell
        n = self._rebuild(n_before, new_keys)
        log.warning("iSAM2 update failed (%s); solver rebuilt from %d factors", first, n)

    def _maybe_back_to_cholesky(self) -> None:
        """After a spell of QR (see ``SmootherConfig.cholesky_retry_updates``), rebuild with Cholesky."""
        if self._qr_until is None or self.n_updates < self._qr_until:
            return
        self._qr_until = None
        self.factorization = Factorization.CHOLESKY
        try:
            n = self._rebuild(self.factors().size(), set())
        except (RuntimeError, ValueError) as exc:  # Cholesky fails on this window too: QR, longer
            self.factorization = Factorization.QR
            self._qr_spell *= 2
            self._qr_until = self.n_updates + self._qr_spell
            first = next((ln for ln in str(exc).splitlines() if ln.strip()), str(exc))
            log.warning("Cholesky failed again on rebuilding (%s); QR kept for %d more updates", first, self._qr_spell)
            return
        self.n_cholesky_returns += 1
        log.info("smoother back to Cholesky after %d updates of QR (rebuilt from %d factors)", self._qr_spell, n)

    def _rebuild(self, n_factors: int, drop_keys: set[int]) -> int:
        """A new solver (with the current factorization) from the first ``n_factors`` factors of
        the graph and the linearization point, less the new keys ``drop_keys``; tells
        ``on_rebuild`` the factors' new indices. Returns the number of factors."""
        old_graph, old_theta = self.factors(), self.theta()
        stamps = dict(self.ifls.timestamps()) if self.fixed_lag else {}
        index_map: dict[int, int] = {}
        graph = gtsam.NonlinearFactorGraph()
        for i in range(min(n_factors, old_graph.size())):
            f = old_graph.at(i)
            if f is None:
                continue
            index_map[i] = graph.size()
            graph.add(f)
        theta = gtsam.Values()
        for k in old_theta.keys():  # noqa: SIM118 (gtsam.Values)
            if k not in drop_keys or k in self._alive:
                theta.insert(k, _value(old_theta, k))
        stamps = {k: t for k, t in stamps.items() if theta.exists(k)}
        before = (self.ifls, self.isam, self._alive)
        self._new_solver()
        try:
            if self.fixed_lag:
                self.ifls.update(graph, theta, stamps, [])
                self._alive = set(self.ifls.timestamps().keys())
            else:
                self.isam.update(graph, theta)
                self._alive = set(theta.keys())
        except (RuntimeError, ValueError):  # the rebuilt system failed too: the solver as it was
            self.ifls, self.isam, self._alive = before
            raise
        if self.on_rebuild is not None:
            self.on_rebuild(index_map)
        if self._maps_since_snapshot is not None:
            self._maps_since_snapshot.append(index_map)
        return graph.size()


def _tangent_dim(key: int) -> int:
    return variable_type(symbol_of(key)).dim

"""The error that a catalog's fixes share, as variables of the smoother (``FixConfig.correlation_model``
"bias"): the EKF's offset states (``ekf.config.FixGateConfig``) in a factor graph.

Successive fixes from one catalog match many of the same entries, so their errors are one error
seen again, not independent draws. Per fix source (``FixConfig.bias_sources``) each applied fix
``j`` gets an offset variable ``O(j)`` (Vector3: x, y, yaw), and its factor measures the pose plus
that offset (``make_fix_factor`` with an offset key), with the fix's unshared noise
(:meth:`reloc.measurements.GlobalFix.unshared`). Between two fixes of a source the offset is a
first-order Gauss-Markov process along the distance driven, ``O(j) = rho O(j-1) + w``, ``rho =
exp(-d / correlation_length_m)`` times the share of the fix's catalog entries that the source's
last fix used too, ``w ~ N(0, (1 - rho^2) bias_share C_match)`` (``C_match`` the fix's match
covariance without the producer's correlation factor); the first fix of a source, or one after the
previous offset has left the fixed-lag window, starts from its stationary prior ``N(0, bias_share
C_match)``. Where ``1 - rho^2`` is below ``1e-9`` the fix reuses the last offset (the same entries,
the same place). Core maths only: the smoother's late-fix stage (``fgslam.smoother.fix_updates``) applies
the factors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import O

from fgslam.smoother.config import FixConfig
from fgslam.smoother.factors import make_gauss_markov_factor
from reloc.backend import offset_report
from reloc.measurements import GlobalFix

_REUSE_BELOW = 1e-9  # 1 - rho^2 below this: the fix takes the last offset itself


@dataclass(frozen=True)
class SourceOffset:
    """A source's latest offset variable ``key``, where the estimate was (``xy``, (2,)), which
    catalog entries (``rows``) its fix used, and the offset's covariance (3, 3) as predicted for
    that fix, before it: the fixes only shrink it, so the next fix's gate takes it as an upper bound
    of the marginal (an offset's marginal cost 8-300 ms on my2020, full history)."""

    key: int
    xy: np.ndarray
    rows: frozenset[int]
    cov: np.ndarray


@dataclass(frozen=True)
class OffsetPlan:
    """How one fix enters with its source's offset: the fix with its unshared noise (``white``),
    the offset's key (new, or the last one reused), the factors and value that bring it in (empty
    when reused), its predicted mean and covariance (3,) / (3, 3) (for the gate), and the rows
    ``G`` (m, 3) through which it shifts the fix's (x, y, yaw[, z])."""

    source: str
    white: GlobalFix
    key: int
    new: bool
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    mean: np.ndarray
    cov: np.ndarray
    G: np.ndarray
    rho: float
    restarted: bool = False  # the source's last offset had left the fixed-lag window


def offset_rows(fix: GlobalFix) -> np.ndarray:
    """(m, 3): how a source offset (x, y, yaw) moves ``fix``'s measured (x, y, yaw[, z]): the
    identity, and for a height read at the fix's (x, y) the terrain's gradient (its row of
    :meth:`GlobalFix.height_model`)."""
    if fix.height is None:
        return np.eye(3)
    g, _ = fix.height_model()
    return np.vstack([np.eye(3), g[None, :]])


class FixOffsets:
    """Per source, the chain of offset variables (see module doc). ``plan`` says how a fix would
    enter (nothing changes); ``commit`` records it once the solver took it."""

    def __init__(self, config: FixConfig) -> None:
        self.config = config
        self.last: dict[str, SourceOffset] = {}
        self.n_keys = 0
        self.n_restarts = 0  # chains restarted because their last offset had left the window

    def applies(self, fix: GlobalFix) -> bool:
        """Whether ``fix`` enters with an offset (the model is on, and its source is one of them)."""
        cfg = self.config
        return cfg.correlation_model == "bias" and fix.source in cfg.bias_sources

    def plan(self, fix: GlobalFix, xy_now: np.ndarray, alive, estimate) -> OffsetPlan:
        """How ``fix`` enters with its source's offset, the estimate being at ``xy_now`` (2,);
        ``alive(key)`` and ``estimate(key)`` (3,) read the solver."""
        cfg = self.config
        match, _ = fix.split_cov()
        share_cov = cfg.bias_share * match
        last = self.last.get(fix.source)
        restarted = last is not None and not alive(last.key)
        rho = 0.0
        if last is not None and not restarted:
            d = float(np.hypot(*(np.asarray(xy_now, float)[:2] - last.xy)))
            rho = math.exp(-d / cfg.correlation_length_m)
            rows = set(fix.catalog_rows)
            if rows and last.rows:  # the share of this fix's entries that the last one used too
                rho *= len(rows & last.rows) / len(rows)
        white = fix.unshared(cfg.bias_share)
        G = offset_rows(white)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if rho <= 0.0:  # a fresh start: the stationary prior
            key = O(self.n_keys)
            graph.add(gtsam.PriorFactorVector(key, np.zeros(3), gtsam.noiseModel.Gaussian.Covariance(share_cov)))
            values.insert(key, np.zeros(3))
            return OffsetPlan(fix.source, white, key, True, graph, values, np.zeros(3), share_cov, G, 0.0, restarted)
        prev_mean, prev_cov = np.asarray(estimate(last.key), float), last.cov
        q = 1.0 - rho * rho
        if q < _REUSE_BELOW:
            return OffsetPlan(fix.source, white, last.key, False, graph, values, prev_mean, prev_cov, G, rho)
        key = O(self.n_keys)
        Q = q * share_cov
        graph.add(make_gauss_markov_factor(last.key, key, rho, Q))
        values.insert(key, rho * prev_mean)
        return OffsetPlan(fix.source, white, key, True, graph, values, rho * prev_mean,
                          rho * rho * prev_cov + Q, G, rho)

    def commit(self, plan: OffsetPlan, fix: GlobalFix, xy_now: np.ndarray) -> None:
        """``plan`` was applied: its offset is the source's latest."""
        if plan.new:
            self.n_keys += 1
        self.n_restarts += plan.restarted
        self.last[plan.source] = SourceOffset(plan.key, np.asarray(xy_now, float)[:2].copy(),
                                              frozenset(int(r) for r in fix.catalog_rows), plan.cov)

    def report(self, alive, estimate, marginal_cov) -> dict:
        """Each source's latest offset (x, y m, yaw deg) and its sigmas, where it is still a variable."""
        out = {}
        for src, last in self.last.items():
            if not alive(last.key):
                continue
            out[src] = offset_report(estimate(last.key), np.sqrt(np.diag(marginal_cov(last.key))))
        return out

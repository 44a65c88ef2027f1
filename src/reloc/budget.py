"""Per-frame observation budget ("feature budget"), shared by both back-ends.

A dense yard puts ~100 rocks in every stereo frame; using all of them costs the EKF
``O(N^2 m)`` per frame (m = 3 x observations) and the smoother one factor each, while the pose
is already pinned by a few dozen well-conditioned ones. After association, a frame uses at most
``max_observations`` associated observations, landmarks already in the map first (confirmed in
the EKF, in the graph for the smoother), then the lowest innovation covariance (nearest,
best-known landmarks); and initialises at most ``max_new`` landmarks, nearest first. What is
left out is only counted: the selection depends on the frame and the state alone, so replays
(EKF late fixes) make the same choice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.config import NonNegativeInt, checked


@dataclass(frozen=True)
@checked()
class ObservationBudget:
    """Bounds per rock frame; 0 = no bound."""

    max_observations: NonNegativeInt = 0  # associated observations used in the update
    max_new: NonNegativeInt = 0  # new landmarks initialised


def select_observations(in_map: np.ndarray, cost: np.ndarray, limit: int) -> np.ndarray:
    """Indices (<= limit,) of the observations to use, ascending: ``in_map`` (k,) bool ones first,
    then the lowest ``cost`` (k,) (e.g. the trace of the innovation covariance, m^2); all if
    ``limit`` is 0 or not exceeded."""
    k = len(cost)
    if limit <= 0 or k <= limit:
        return np.arange(k)
    order = np.lexsort((np.asarray(cost, dtype=float), ~np.asarray(in_map, dtype=bool)))
    return np.sort(order[:limit])


def innovation_trace(S_hat: np.ndarray, R_z: np.ndarray) -> np.ndarray:
    """(k,) trace of ``S_hat + R_z`` for k pairs of (k, 3, 3) covariances (m^2)."""
    return np.trace(S_hat, axis1=1, axis2=2) + np.trace(R_z, axis1=1, axis2=2)

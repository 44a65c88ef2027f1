"""Keyframe bookkeeping: times, the keyframe policy, the online (causal) history and the poses
frozen when a keyframe leaves the fixed-lag window."""

from __future__ import annotations

import numpy as np

from fgslam.smoother.config import KeyframeConfig
from fgslam.smoother.odometry_factors import OdometryAccumulator
from reloc.rows import RowBuffer

_POSE_COV = 16 + 36  # a row: T_world_base (4, 4) then its covariance (6, 6), both flattened


def keyframe_due(acc: OdometryAccumulator, cfg: KeyframeConfig) -> bool:
    """Whether the motion since the last keyframe calls for a new one (distance, yaw or time)."""
    return (
        acc.distance_m >= cfg.distance_m
        or acc.yaw_change_rad() >= cfg.yaw_rad
        or acc.t_now - acc.t_kf >= cfg.interval_s
    )


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class KeyframeStore:
    """Keyframe ``i`` is the GTSAM variable ``X(i)`` at time ``t[i]``.

    ``online`` keeps, per keyframe, the estimate and covariance the smoother had right after adding
    it (the causal estimate, protocol convention); ``frozen`` the last smoothed estimate of a
    keyframe that was marginalized by the fixed-lag smoother.

    A kilometre traverse makes a keyframe a second, ~10^5 of them: the times are one growing
    array (``t`` is a view of it, no list to convert at every keyframe) and the poses with their
    covariances rows of :class:`reloc.rows.RowBuffer` (416 B a pose, where two small arrays in a
    list cost ~1 kB). Poses come back as read-only views.
    """

    def __init__(self) -> None:
        self._t = np.empty(256)
        self._n = 0
        self._online = RowBuffer(_POSE_COV)
        self._frozen = RowBuffer(_POSE_COV)
        self._frozen_row = np.full(256, -1, dtype=np.int64)  # keyframe -> its row in _frozen (-1: none)

    def __len__(self) -> int:
        return self._n

    @property
    def t(self) -> np.ndarray:
        """Keyframe times (s), oldest first: a read-only view, valid as long as no keyframe is added."""
        return _read_only(self._t[: self._n])

    def add(self, t: float) -> int:
        """Register a keyframe at ``t`` s; returns its index."""
        if self._n == len(self._t):
            self._t = np.concatenate([self._t, np.empty(len(self._t))])
            self._frozen_row = np.concatenate([self._frozen_row, np.full(len(self._frozen_row), -1, dtype=np.int64)])
        self._t[self._n] = float(t)
        self._n += 1
        return self._n - 1

    def before(self, t: float) -> int:
        """Index of the latest keyframe at or before ``t`` (-1 if none)."""
        return int(np.searchsorted(self._t[: self._n], t, side="right")) - 1

    # ---------------------------------------------------------------- the causal estimates
    def record_online(self, T_world_base: np.ndarray, cov_world: np.ndarray) -> None:
        """Store the causal estimate (4, 4) / (6, 6) of the newest keyframe."""
        self._online.append(np.concatenate([np.ravel(T_world_base), np.ravel(cov_world)]))

    @property
    def n_online(self) -> int:
        """How many keyframes have their causal estimate recorded (the first ``n_online``)."""
        return len(self._online)

    def online_T(self, i: int) -> np.ndarray:
        """The causal pose (4, 4) of keyframe ``i`` (read-only view)."""
        return _read_only(self._online.row(i)[:16].reshape(4, 4))

    def online_cov(self, i: int) -> np.ndarray:
        """The causal covariance (6, 6, protocol convention) of keyframe ``i`` (read-only view)."""
        return _read_only(self._online.row(i)[16:].reshape(6, 6))

    def online_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t (N,), T (N, 4, 4), cov (N, 6, 6)) of every recorded causal estimate (copies)."""
        rows = self._online.array()
        n = len(rows)
        return self._t[:n].copy(), rows[:, :16].reshape(n, 4, 4), rows[:, 16:].reshape(n, 6, 6)

    # ---------------------------------------------------------------- frozen on marginalization
    def freeze(self, i: int, T_world_base: np.ndarray, cov_world: np.ndarray) -> None:
        """Keep keyframe ``i``'s last smoothed pose (4, 4) and covariance (6, 6) as it leaves the window."""
        self._frozen_row[i] = len(self._frozen)  # frozen again: the newer estimate wins
        self._frozen.append(np.concatenate([np.ravel(T_world_base), np.ravel(cov_world)]))

    def is_frozen(self, i: int) -> bool:
        return bool(self._frozen_row[i] >= 0)

    def frozen(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The pose (4, 4) and covariance (6, 6) keyframe ``i`` was frozen with (read-only views)."""
        r = int(self._frozen_row[i])
        if r < 0:
            raise KeyError(f"keyframe {i} is not frozen")
        row = self._frozen.row(r)
        return _read_only(row[:16].reshape(4, 4)), _read_only(row[16:].reshape(6, 6))

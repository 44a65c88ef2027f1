"""Temporal persistence of associations, shared by both back-ends: a rock is detected again where
it was a moment ago; terrain clutter is not.

A detector's false detections (clutter) are independent from frame to frame, but once one falls
inside a landmark's association gate it looks like a detection of that landmark, and its
innovation is spread over the gate around the *predicted* position: it confirms the prediction.
Where the rocks go undetected (a plain with no rock in view, poor light) while the clutter goes
on, a back-end then keeps confirming its own dead reckoning and its covariance stops growing
while its error grows (``fgslam bench faults``, ``no_rocks``: position NEES 14-156).

The test: an association of landmark ``j`` at ``t`` is used only when one of ``j``'s detections
of the last ``window_s`` seconds (associated or initialising, used or not) lies at the same world
position within the two detections' covariances, plus the pose change between the two frames
that the odometry may not model (per axis: ``slack_m``, and ``slack_rad`` times the point's
range; :func:`slack_variance`): squared Mahalanobis distance below ``gate_chi2``. Every
association is remembered, used or not, so the first detection of a rock seen again after a gap only waits for
the next frame; a clutter point inside a gate needs a second one, in the next frames, at the same
place within the (much smaller) measurement covariance.

New landmarks get the same test (:class:`PendingDetections`): a detection far from every
landmark waits as a *first sighting* for ``window_s``, and becomes a landmark only when a later
frame detects something at the same world position. Clutter then never reaches a back-end's
state, where in the EKF every tentative landmark costs a state slot and, once the state is full,
evicts a mapped rock (a 2-minute stretch of clutter evicted every landmark around the rover, and
the filter could not re-find them when the rocks came back). Core maths only: no I/O.
"""

from __future__ import annotations

import numpy as np

from reloc.association import AssociationConfig, pairwise_d2, uncertain_pairs

_SWEEP_EVERY_S = 10.0


def slack_variance(slack_m: float, slack_rad: float, range_m) -> np.ndarray:
    """Per-axis variance (n,) of the pose change between two frames at a point ``range_m`` (n,)
    away: ``slack_m`` of translation and ``slack_rad`` of rotation (a heading drift the odometry
    does not model moves a far point more than a near one)."""
    r = np.asarray(range_m, dtype=float).reshape(-1)
    return slack_m * slack_m + (slack_rad * r) ** 2


def persistence_slack(config: AssociationConfig, z_base: np.ndarray) -> np.ndarray:
    """:func:`slack_variance` (k,) of ``config``'s persistence settings for detections ``z_base``
    (k, 3) in base_link (their range from the rover)."""
    r = np.linalg.norm(np.reshape(np.asarray(z_base, dtype=float), (-1, 3)), axis=1)
    return slack_variance(config.persistence_slack_m, config.persistence_slack_rad, r)


def persistence_agree(config: AssociationConfig, S_hat: np.ndarray, R_z: np.ndarray) -> np.ndarray:
    """(k,) how many earlier detections must agree with each pair (predicted covariance ``S_hat``
    (k, 3, 3), measurement covariance ``R_z`` (k, 3, 3)): ``config.persistence_n_uncertain`` where
    the prediction is far less certain than the measurement (:func:`reloc.association.uncertain_pairs`),
    else 1."""
    return np.where(uncertain_pairs(config, S_hat, R_z), config.persistence_n_uncertain, 1)


class RecentDetections:
    """Per landmark id, its detections of the last seconds in world coordinates (position (3,),
    covariance (3, 3)), at most ``depth`` each. :meth:`copy` gives an independent snapshot (the
    EKF's checkpoints)."""

    def __init__(self, depth: int = 4) -> None:
        if depth < 1:
            raise ValueError(f"RecentDetections: depth must be >= 1, got {depth}")
        self.depth = depth
        self._d: dict[int, list[tuple[float, np.ndarray, np.ndarray]]] = {}
        self._t_sweep = -np.inf
        self._horizon_s = 0.0

    def __len__(self) -> int:
        return len(self._d)

    def copy(self) -> RecentDetections:
        other = RecentDetections(self.depth)
        other._d = {k: list(v) for k, v in self._d.items()}  # entries are never mutated
        other._t_sweep, other._horizon_s = self._t_sweep, self._horizon_s
        return other

    def record(self, ids: np.ndarray, t: float, xyz_world: np.ndarray, cov_world: np.ndarray) -> None:
        """Remember detections (k,) of landmarks ``ids`` at ``t`` without testing them (a landmark's
        initialising detection)."""
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (-1, 3))
        cov = np.reshape(np.asarray(cov_world, dtype=float), (-1, 3, 3))
        for i, lid in enumerate(np.asarray(ids, dtype=int).reshape(-1)):
            entries = self._d.setdefault(int(lid), [])
            entries.append((float(t), xyz[i].copy(), cov[i].copy()))
            del entries[: -self.depth]

    def confirm(self, ids: np.ndarray, t: float, xyz_world: np.ndarray, cov_world: np.ndarray,
                window_s: float, gate_chi2: float, slack_var=0.0, min_agree=1) -> np.ndarray:
        """:meth:`test`, then :meth:`record` of the same detections (a back-end that places them
        no better after its update)."""
        ok = self.test(ids, t, xyz_world, cov_world, window_s, gate_chi2, slack_var, min_agree)
        if window_s > 0:
            self.record(ids, t, xyz_world, cov_world)
        return ok

    def test(self, ids: np.ndarray, t: float, xyz_world: np.ndarray, cov_world: np.ndarray,
             window_s: float, gate_chi2: float, slack_var=0.0, min_agree=1) -> np.ndarray:
        """(k,) bool: whether each detection (``xyz_world`` (k, 3), ``cov_world`` (k, 3, 3)) of
        landmark ``ids`` (k,) at ``t`` has an earlier detection of the same landmark within
        ``window_s`` (strictly before ``t``) inside ``gate_chi2`` (on the two covariances plus
        ``slack_var``, scalar or (k,), per axis: :func:`slack_variance`). Remembers nothing:
        :meth:`record` them once placed (an EKF after its update: placed with the pose the
        frame's update gave, the next frame compares against where the rocks are, not against
        where the pose before the correction put them; a test biased against its own corrections
        made the EKF inconsistent). ``min_agree`` (scalar or (k,)): how many earlier detections
        in the window must agree (a detection whose landmark is predicted far less certainly
        than it is measured asks for two: see ``AssociationConfig.persistence_n_uncertain``).
        ``window_s`` 0: every detection passes."""
        ids = np.asarray(ids, dtype=int).reshape(-1)
        k = ids.size
        if window_s <= 0 or k == 0:
            return np.ones(k, dtype=bool)
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (k, 3))
        cov = np.reshape(np.asarray(cov_world, dtype=float), (k, 3, 3))
        slack = np.broadcast_to(np.asarray(slack_var, dtype=float), (k,))
        need = np.broadcast_to(np.asarray(min_agree, dtype=int), (k,))
        ok = np.zeros(k, dtype=bool)
        rows, x0, c0 = [], [], []  # every (detection, earlier detection) pair in the window
        for i, lid in enumerate(ids):
            for t0, x, c in self._d.get(int(lid), ()):
                if t - window_s <= t0 < t:
                    rows.append(i)
                    x0.append(x)
                    c0.append(c)
        if rows:
            r = np.array(rows)
            d = xyz[r] - np.array(x0)
            S = cov[r] + np.array(c0) + slack[r, None, None] * np.eye(3)
            d2 = np.einsum("ki,ki->k", d, np.linalg.solve(S, d[..., None])[..., 0])
            agree = np.bincount(r[d2 <= gate_chi2], minlength=k)
            ok = agree >= need
        self._horizon_s = max(self._horizon_s, window_s)
        if t - self._t_sweep > _SWEEP_EVERY_S:
            self.sweep(t)
        return ok

    def seen(self, ids: np.ndarray, t: float, window_s: float) -> np.ndarray:
        """(k,) bool: whether each landmark of ``ids`` has a detection recorded within ``window_s``
        before ``t`` (strictly before), wherever it was."""
        return np.array([any(t - window_s <= e[0] < t for e in self._d.get(int(lid), ()))
                         for lid in np.asarray(ids, dtype=int).reshape(-1)], dtype=bool)

    def sweep(self, t: float) -> None:
        """Forget the landmarks with no detection within the longest window used so far."""
        self._t_sweep = t
        old = t - self._horizon_s
        self._d = {k: v for k, v in self._d.items() if v[-1][0] >= old}

    def forget(self, ids) -> None:
        """Drop the records of landmarks ``ids`` (they left the map)."""
        for lid in np.asarray(ids, dtype=int).reshape(-1):
            self._d.pop(int(lid), None)


class _Points:
    """Detections in world coordinates with their times: ``t`` (n,), ``xyz`` (n, 3), ``cov``
    (n, 3, 3). :meth:`copy` gives an independent snapshot."""

    def __init__(self) -> None:
        self.t = np.zeros(0)
        self.xyz = np.zeros((0, 3))
        self.cov = np.zeros((0, 3, 3))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def copy(self):
        other = type(self)()
        other.t, other.xyz, other.cov = self.t.copy(), self.xyz.copy(), self.cov.copy()
        return other


class PendingDetections(_Points):
    """First sightings: detections that would start a landmark, kept for a few seconds until a
    later frame confirms one at the same world position (see module doc). :meth:`copy` gives an
    independent snapshot."""

    def confirm(self, t: float, xyz_world: np.ndarray, cov_world: np.ndarray, window_s: float,
                gate_chi2: float, slack_var=0.0) -> np.ndarray:
        """(n,) bool: which of the would-be landmarks ``xyz_world`` (n, 3), ``cov_world`` (n, 3, 3)
        at ``t`` repeat a first sighting of the last ``window_s`` seconds (strictly before ``t``)
        within ``gate_chi2``. Each first sighting confirms at most one detection (the nearest) and
        is then used up; the others of this frame become first sightings. ``slack_var`` as in
        :meth:`RecentDetections.confirm`. ``window_s`` 0: all pass."""
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (-1, 3))
        cov = np.reshape(np.asarray(cov_world, dtype=float), (-1, 3, 3))
        n = xyz.shape[0]
        if window_s <= 0:
            return np.ones(n, dtype=bool)
        live = (self.t >= t - window_s) & (self.t < t)
        self.t, self.xyz, self.cov = self.t[live], self.xyz[live], self.cov[live]
        ok = np.zeros(n, dtype=bool)
        if n and len(self):
            slack = np.broadcast_to(np.asarray(slack_var, dtype=float), (n,))
            d2 = pairwise_d2(xyz, cov + slack[:, None, None] * np.eye(3), self.xyz, self.cov)
            used = np.zeros(len(self), dtype=bool)
            for i in np.argsort(d2.min(axis=1), kind="stable"):  # the closest pairs first
                cand = np.flatnonzero((d2[i] <= gate_chi2) & ~used)
                if cand.size:
                    used[cand[np.argmin(d2[i, cand])]] = True
                    ok[i] = True
            self.t, self.xyz, self.cov = self.t[~used], self.xyz[~used], self.cov[~used]
        self.t = np.concatenate([self.t, np.full(int((~ok).sum()), float(t))])
        self.xyz = np.vstack([self.xyz, xyz[~ok]])
        self.cov = np.concatenate([self.cov, cov[~ok]])
        return ok


class RecentFrames(_Points):
    """Every detection of the last seconds in world coordinates, frame by frame, whatever became
    of it (associated, ambiguous, refused as one of too few uncertain pairs). An uncertain pair
    asks for ``persistence_n_uncertain`` earlier detections of its landmark that agree; where the
    rover comes back to its map after a long blind stretch, its gates are metres wide, and a
    sparse field's frames of one or two detections are refused whole (``min_pairs_uncertain``),
    so its landmarks are associated only every few frames and never twice in the window: the
    rover is never re-placed (``AssociationConfig.persistence_any_detection``). What the rule is
    for holds as well by place: a rock is detected again where it was, clutter is not; this
    counts the earlier frames that held a detection at the pair's world position, associated or
    not (asked only for a landmark with no detection at all in the window: by place, a rock of a
    dense field in the wide gate of its neighbour would pass as well, which the landmark's own
    record rules out). :meth:`copy` gives an independent snapshot."""

    def record(self, t: float, xyz_world: np.ndarray, cov_world: np.ndarray, window_s: float) -> None:
        """Remember one frame's detections ``xyz_world`` (n, 3), ``cov_world`` (n, 3, 3) at ``t``;
        forget those older than ``window_s``."""
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (-1, 3))
        cov = np.reshape(np.asarray(cov_world, dtype=float), (-1, 3, 3))
        live = self.t >= t - window_s
        self.t = np.concatenate([self.t[live], np.full(xyz.shape[0], float(t))])
        self.xyz = np.vstack([self.xyz[live], xyz])
        self.cov = np.concatenate([self.cov[live], cov])

    def count(self, t: float, xyz_world: np.ndarray, cov_world: np.ndarray, window_s: float, gate_chi2: float,
              slack_var=0.0) -> np.ndarray:
        """(k,) int: for each detection ``xyz_world`` (k, 3), ``cov_world`` (k, 3, 3) at ``t``, the
        number of distinct earlier frames (within ``window_s``, strictly before ``t``) holding a
        detection inside ``gate_chi2`` of it (on the two covariances plus ``slack_var``, scalar or
        (k,), per axis, as :meth:`RecentDetections.test`)."""
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (-1, 3))
        cov = np.reshape(np.asarray(cov_world, dtype=float), (-1, 3, 3))
        k = xyz.shape[0]
        live = np.flatnonzero((self.t >= t - window_s) & (self.t < t))
        if k == 0 or live.size == 0:
            return np.zeros(k, dtype=int)
        slack = np.broadcast_to(np.asarray(slack_var, dtype=float), (k,))
        d2 = pairwise_d2(xyz, cov + slack[:, None, None] * np.eye(3), self.xyz[live], self.cov[live], gate_chi2)
        frames = self.t[live]
        return np.array([np.unique(frames[d2[i] <= gate_chi2]).size for i in range(k)], dtype=int)


def place_agrees(ok: np.ndarray, need: np.ndarray, ids, t: float, xyz_world: np.ndarray,
                 cov_world: np.ndarray, recent: RecentDetections, frames: RecentFrames, window_s: float,
                 gate_chi2: float, slack_var) -> np.ndarray:
    """``ok`` (k,) of :meth:`RecentDetections.test` with the place rule
    (``AssociationConfig.persistence_any_detection``, :class:`RecentFrames`): a pair refused there
    that needed more than one agreeing detection (``need`` (k,)), of a landmark (``ids`` (k,)) with
    no detection at all in the window, passes when as many earlier frames held a detection at its
    world position (``xyz_world`` (k, 3), ``cov_world`` (k, 3, 3), ``slack_var`` (k,)). One rule
    for both back-ends; returns a new array."""
    ok = np.array(ok, dtype=bool)
    need = np.broadcast_to(np.asarray(need, dtype=int), ok.shape)
    retry = np.flatnonzero(~ok & (need > 1))
    if retry.size:
        ids = np.asarray(ids, dtype=int).reshape(-1)
        retry = retry[~recent.seen(ids[retry], t, window_s)]
    if retry.size:
        xyz = np.reshape(np.asarray(xyz_world, dtype=float), (-1, 3))[retry]
        cov = np.reshape(np.asarray(cov_world, dtype=float), (-1, 3, 3))[retry]
        slack = np.broadcast_to(np.asarray(slack_var, dtype=float), ok.shape)[retry]
        ok[retry] = frames.count(t, xyz, cov, window_s, gate_chi2, slack) >= need[retry]
    return ok

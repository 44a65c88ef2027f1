"""Rock landmarks of the smoother: association through the shared front-end, candidates until
constrained, insertion into the graph, cached positions and covariances.

A detection not associated with any landmark starts a *candidate* (not in the graph). Its
observations are kept, and once ``min_obs_to_insert`` of them come from distinct keyframes the
rock is constrained in 3D from more than one viewpoint: it becomes a Point3 ``L(id)`` with all its
factors. Association needs predicted measurements and their covariance ``S_hat``; iSAM2 marginals
per landmark per frame would cost more than the whole update, so the store keeps, per landmark,
an information-fused covariance of its observations (pose taken as exact, i.e. relative to the
observing poses) and adds the odometry uncertainty since the last keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fgslam.smoother.config import LandmarkConfig
from reloc.association import associate
from reloc.budget import innovation_trace, select_observations
from reloc.covariance import psd_part
from reloc.geometry import skew
from reloc.landmark_model import point_in_base, point_to_world
from reloc.persistence import RecentDetections, RecentFrames, persistence_agree, persistence_slack, place_agrees

CANDIDATE, ACTIVE, RETIRED = 0, 1, 2
_VIEW_SLACK_M = 1.0  # motion allowed from the view cache's centre (keyframes are <= 0.5 m apart)


def nested_increments(t_last: np.ndarray, cov_growth) -> tuple[np.ndarray, np.ndarray]:
    """The pose growth shared by landmarks last seen at ``t_last`` (k,), as nested increments:
    ``rank`` (k,) (0 for the newest time) and ``inc`` (R, 6, 6), so that the growth shared by
    landmarks ``a`` and ``b`` (the growth since the later of their two times, ``cov_growth(t)``
    (k,) -> (k, 6, 6)) is ``inc[: min(rank[a], rank[b]) + 1].sum(0)``. Each growth is the positive
    part of a difference of covariances, which is not ordered in time, and the block matrix of the
    growths themselves was indefinite after a blind spell (joint distances below zero, so any set
    of pairs passed the joint-compatibility test). Here, from the newest time to the oldest, each
    adds the positive part of what its growth holds beyond the sum so far: every block is at least
    the growth it stands for, and a sum of such nested increments is a covariance."""
    t_last = np.asarray(t_last, dtype=float)
    times, inverse = np.unique(-t_last, return_inverse=True)  # newest first
    G = cov_growth(-times)
    acc = np.zeros((6, 6))
    inc = np.empty_like(G)
    for r in range(len(times)):
        inc[r] = psd_part(G[r] - acc)
        acc = acc + inc[r]
    return inverse.reshape(-1), inc


def nested_growth(t_last: np.ndarray, cov_growth) -> np.ndarray:
    """(k, k, 6, 6): the pose growth shared by each two landmarks last seen at ``t_last`` (k,)
    (:func:`nested_increments`, summed)."""
    rank, inc = nested_increments(t_last, cov_growth)
    shared = np.cumsum(inc, axis=0)
    return shared[np.minimum(rank[:, None], rank[None, :])]


def shared_pose_cov(H: np.ndarray, P: np.ndarray, rank: np.ndarray | None = None,
                    inc: np.ndarray | None = None) -> np.ndarray:
    """(3k, 3k): ``H`` (k, 3, 6) times the pose covariance the k measurements share: ``P`` (6, 6)
    common to all, plus the nested growth (:func:`nested_increments`) where given. Increment
    ``r`` is shared by the landmarks of rank ``r`` and older, so it adds one low-rank term
    ``J_r inc_r J_r^T`` (``J_r``: ``H`` with the newer rows zeroed): R products of (3k, 6) instead
    of the (k, k, 6, 6) block tensor (~6 ms a frame on a kilometre traverse's 80 pairs)."""
    J = H.reshape(-1, 6)
    S = J @ P @ J.T
    if inc is not None:
        row_rank = np.repeat(rank, 3)
        for r in range(len(inc)):
            Jr = np.where((row_rank >= r)[:, None], J, 0.0)
            S += Jr @ inc[r] @ Jr.T
    return S


@dataclass
class LandmarkRecord:
    """One rock: world position (3,) m and covariance (3, 3) m^2, status, observation counts."""

    lid: int
    xyz_world_m: np.ndarray
    cov_world_m2: np.ndarray
    size_sum_m: float
    n_obs: int
    t_first: float
    t_last: float
    status: int = CANDIDATE
    pending: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (kf, z, R_z)


@dataclass(frozen=True)
class FrameAssociation:
    """What one rock frame produced: observations of graph landmarks ``(lid, z (3,), R_z (3, 3))``,
    landmarks ready to enter the graph, and report counts."""

    observed: list[tuple[int, np.ndarray, np.ndarray]]
    to_insert: list[LandmarkRecord]
    n_associated: int
    n_new: int
    n_rejected: int


class LandmarkStore:
    """All landmarks by id; the smoother owns the graph side."""

    def __init__(self, cfg: LandmarkConfig) -> None:
        self.cfg = cfg
        self.records: dict[int, LandmarkRecord] = {}
        self.live: dict[int, LandmarkRecord] = {}  # candidates and graph landmarks (not retired)
        self._retired: list[int] = []
        self.next_id = 0
        self.n_budget_skipped = 0  # observations of graph landmarks left out by the budget
        self.n_budget_new_skipped = 0  # insertions deferred by the budget (the candidate waits)
        self.recent = RecentDetections()  # recent detections per landmark (reloc.persistence)
        self.frames = RecentFrames()  # every recent detection by place (persistence_any_detection)
        self.n_not_persistent = 0  # associations left out: no detection at that place just before
        self.n_jc_dropped = 0  # pairs the joint-compatibility test refused
        # live records near the last keyframe, in creation order (see set_view_cache)
        self._view: list[LandmarkRecord] | None = None
        self._view_center = np.zeros(3)

    def nearby(self, p_world: np.ndarray) -> list[LandmarkRecord]:
        """Candidates and graph landmarks within the association range of ``p_world`` (3,)."""
        out = list(self.live.values())
        if not out:
            return out
        xyz = np.array([r.xyz_world_m for r in out])
        near = np.linalg.norm(xyz[:, :2] - p_world[:2], axis=1) <= self.cfg.association.max_range_m + 2.0
        return [out[i] for i in np.flatnonzero(near)]

    def set_view_cache(self, p_world: np.ndarray) -> None:
        """Keep the live landmarks within ``max_range + 1.5 + 2 * _VIEW_SLACK_M`` of ``p_world``
        (3,): :meth:`in_view` from any pose within ``_VIEW_SLACK_M`` of it then filters this short
        list instead of every landmark (same result; the other slack covers landmarks moving)."""
        self._view = None
        recs = list(self.live.values())
        if recs:
            d = np.linalg.norm(np.array([r.xyz_world_m for r in recs]) - p_world, axis=1)
            keep = d <= self.cfg.association.max_range_m + 1.5 + 2.0 * _VIEW_SLACK_M
            recs = [recs[i] for i in np.flatnonzero(keep)]
        self._view = recs
        self._view_center = np.array(p_world, dtype=float)

    def in_view(self, R_world_base: np.ndarray, p_world: np.ndarray) -> list[LandmarkRecord]:
        """Live landmarks that can be associated from this pose: in range and not behind."""
        if self._view is not None and np.linalg.norm(p_world - self._view_center) <= _VIEW_SLACK_M:
            out = list(self._view)
        else:
            out = list(self.live.values())
        if not out:
            return out
        z = point_in_base(R_world_base, p_world, np.array([r.xyz_world_m for r in out]))
        ok = (np.linalg.norm(z, axis=1) <= self.cfg.association.max_range_m + 1.5) & (z[:, 0] > -1.0)
        return [out[i] for i in np.flatnonzero(ok)]

    def associate_frame(
        self,
        t: float,
        kf: int,
        T_world_base: np.ndarray,
        cov_rel_pose: np.ndarray,
        z_base: np.ndarray,
        R_z: np.ndarray,
        size_m: np.ndarray,
        z_kf: np.ndarray,
        R_kf: np.ndarray,
        cov_growth=None,
    ) -> FrameAssociation:
        """Associate detections ``z_base`` (N, 3) with covariance ``R_z`` (N, 3, 3) seen from the
        keyframe ``kf`` at ``T_world_base`` (4, 4); ``cov_rel_pose`` (6, 6, GTSAM body frame) is
        the pose uncertainty relative to the landmarks (odometry since the keyframe). ``z_kf`` (N, 3)
        and ``R_kf`` (N, 3, 3) are the same detections moved onto the keyframe, for the factors.
        ``cov_growth(t_last)`` (K,) -> (K, 6, 6) adds to each candidate's pose uncertainty what the
        pose gained since the landmark was last seen (see :class:`fgslam.smoother.kinds.KeyframeFrame`)."""
        R, p = T_world_base[:3, :3], T_world_base[:3, 3]
        # the association's error model (LandmarkConfig.association_cov_scale): the detections' and
        # the landmarks' covariances times s in the gates, the joint test and the persistence
        # test; the records fuse the detector's, which the landmark map reports
        s = self.cfg.association_cov_scale
        R_det, R_z = R_z, R_z * s
        rng = np.linalg.norm(z_base, axis=1)
        usable = rng >= self.cfg.min_range_m
        z_base, R_z, R_det, size_m = z_base[usable], R_z[usable], R_det[usable], size_m[usable]
        z_kf, R_kf = z_kf[usable], R_kf[usable]
        n_rejected = int((~usable).sum())
        cands = self.in_view(R, p)
        if cands:
            l_world = np.array([r.xyz_world_m for r in cands])
            zhat = point_in_base(R, p, l_world)
            C_l = np.array([r.cov_world_m2 for r in cands])
            S_hat = s * (R.T @ C_l @ R)
            # pose part in the body frame: dz = [zhat]x domega - dv
            H = np.zeros((len(cands), 3, 6))
            H[:, :, :3] = skew(zhat)
            H[:, :, 3:] = -np.eye(3)
            S_l = S_hat
            grow = cov_growth is not None and self.cfg.gate_with_cov_growth
            t_last = np.array([r.t_last for r in cands])
            P = cov_rel_pose + cov_growth(t_last) if grow else cov_rel_pose
            S_hat = S_l + H @ P @ np.swapaxes(H, 1, 2)
            sizes = np.array([r.size_sum_m / max(r.n_obs, 1) for r in cands])

            def joint_cov(det: np.ndarray, ci: np.ndarray) -> np.ndarray:
                """The pairs' full innovation covariance: the pose error since a keyframe is shared
                by every landmark seen before it (the growth since the later of two last-seen
                keyframes, and the odometry since the current keyframe, are common to both)."""
                k = det.size
                S = shared_pose_cov(H[ci], cov_rel_pose, *(nested_increments(t_last[ci], cov_growth) if grow else ()))
                S.reshape(k, 3, k, 3)[np.arange(k), :, np.arange(k), :] += S_l[ci] + R_z[det]
                return S
        else:
            zhat, S_hat, sizes, joint_cov = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), None
        a = associate(z_base, R_z, zhat, S_hat, self.cfg.association, size_m, sizes, joint_cov)
        self.n_jc_dropped += a.n_jc_dropped
        observed: list[tuple[int, np.ndarray, np.ndarray]] = []
        to_insert: list[LandmarkRecord] = []
        l_new, c_det = point_to_world(R, p, z_base, R_det)
        c_new = s * c_det  # the detections' world covariance as the association takes it
        matched = np.flatnonzero(a.landmark_of >= 0)
        ac = self.cfg.association
        n_not_persistent = 0
        if matched.size and ac.persistence_s > 0:  # clutter inside a gate: not seen there before
            ids = [cands[int(a.landmark_of[i])].lid for i in matched]
            slack = persistence_slack(ac, z_base[matched])
            need = persistence_agree(ac, S_hat[a.landmark_of[matched]], R_z[matched])
            ok = self.recent.confirm(ids, t, l_new[matched], c_new[matched], ac.persistence_s, ac.gate_chi2,
                                     slack, need)
            if ac.persistence_any_detection:  # seen() looks strictly before t: this frame's record is not counted
                ok = place_agrees(ok, need, ids, t, l_new[matched], c_new[matched], self.recent, self.frames,
                                  ac.persistence_s, ac.gate_chi2, slack)
            n_not_persistent = int(matched.size - ok.sum())
            self.n_not_persistent += n_not_persistent
            matched = matched[ok]
        skipped = self._over_budget(matched, [cands[int(j)] for j in a.landmark_of[matched]], S_hat, R_z, a)
        if skipped.size:  # seen, but no factor: counted, covariance not fused
            for i in skipped:
                rec = cands[int(a.landmark_of[i])]
                rec.size_sum_m += float(size_m[i])
                rec.n_obs += 1
                rec.t_last = t
            matched = np.setdiff1d(matched, skipped)
        if matched.size:
            self._fuse_batch([cands[int(a.landmark_of[i])] for i in matched], l_new[matched], c_det[matched],
                             size_m[matched], t)
        for i in matched:
            rec = cands[int(a.landmark_of[i])]
            if rec.status == ACTIVE:
                observed.append((rec.lid, z_kf[i], R_kf[i]))
            else:
                if not rec.pending or rec.pending[-1][0] != kf:
                    rec.pending.append((kf, z_kf[i], R_kf[i]))
                if len(rec.pending) >= self.cfg.min_obs_to_insert:
                    to_insert.append(rec)
        room = self._insert_room(sum(r.status == ACTIVE for r in cands))
        if room < len(to_insert):  # best-constrained candidates first; the rest wait, pending
            order = np.argsort([np.trace(r.cov_world_m2) for r in to_insert], kind="stable")
            self.n_budget_new_skipped += len(to_insert) - room
            to_insert = [to_insert[k] for k in np.sort(order[:room])]
        for i in range(z_base.shape[0]):
            if a.landmark_of[i] < 0 and a.is_new[i]:
                rec = LandmarkRecord(self.next_id, l_new[i], c_det[i], float(size_m[i]), 1, t, t)
                rec.pending.append((kf, z_kf[i], R_kf[i]))
                self.records[rec.lid] = rec
                self.live[rec.lid] = rec
                if ac.persistence_s > 0:
                    self.recent.record([rec.lid], t, l_new[i], c_new[i])
                if self._view is not None:
                    self._view.append(rec)
                self.next_id += 1
        if ac.persistence_s > 0 and ac.persistence_any_detection:
            self.frames.record(t, l_new, c_new, ac.persistence_s)
        n_new = int(a.is_new.sum())
        return FrameAssociation(observed, to_insert, int(matched.size), n_new,
                                n_rejected + a.n_ambiguous + a.n_out_of_range + int(skipped.size) + n_not_persistent)

    def _insert_room(self, n_in_view: int) -> int | float:
        """How many candidates may enter the graph in a frame whose view holds ``n_in_view`` graph
        landmarks: any number while fewer than ``dense_view`` (a sparse yard is never held back),
        beyond it at most ``max_new`` per frame (0 = no bound)."""
        max_new, dense = self.cfg.budget.max_new, self.cfg.dense_view
        if max_new <= 0 or (dense > 0 and n_in_view < dense):
            return np.inf
        return max_new

    def _over_budget(self, matched: np.ndarray, recs: list[LandmarkRecord], S_hat: np.ndarray,
                     R_z: np.ndarray, a) -> np.ndarray:
        """Detections (subset of ``matched``) of graph landmarks beyond ``max_observations`` (lowest
        innovation covariance kept); candidates' observations cost no factor and are never skipped."""
        active = np.array([r.status == ACTIVE for r in recs], dtype=bool)
        limit = self.cfg.budget.max_observations
        if limit <= 0 or active.sum() <= limit:
            return matched[:0]
        det = matched[active]
        keep = select_observations(np.ones(det.size, dtype=bool),
                                   innovation_trace(S_hat[a.landmark_of[det]], R_z[det]), limit)
        skipped = np.delete(det, keep)
        self.n_budget_skipped += int(skipped.size)
        return skipped

    @classmethod
    def _fuse_batch(cls, recs: list[LandmarkRecord], l: np.ndarray, C: np.ndarray, size: np.ndarray,
                    t: float) -> None:
        """:meth:`_fuse` of K detections (K, 3) / (K, 3, 3) into K records, one batched inverse."""
        if len({id(r) for r in recs}) < len(recs):  # one rock matched twice: fuse in order
            for rec, li, Ci, si in zip(recs, l, C, size):
                cls._fuse(rec, li, Ci, float(si), t)
            return
        x_old = np.array([r.xyz_world_m for r in recs])
        info = np.linalg.inv(np.concatenate([np.array([r.cov_world_m2 for r in recs]), C]))
        info_old, info_new = info[: len(recs)], info[len(recs):]
        cov = np.linalg.inv(info_old + info_new)
        x = np.einsum("kij,kj->ki", cov, np.einsum("kij,kj->ki", info_old, x_old) + np.einsum("kij,kj->ki", info_new, l))
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        for k, rec in enumerate(recs):
            if rec.status != ACTIVE:  # graph landmarks take their position from the solver
                rec.xyz_world_m = x[k]
            rec.cov_world_m2 = cov[k]
            rec.size_sum_m += float(size[k])
            rec.n_obs += 1
            rec.t_last = t

    @staticmethod
    def _fuse(rec: LandmarkRecord, l: np.ndarray, C: np.ndarray, size: float, t: float) -> None:
        info_old, info_new = np.linalg.inv(rec.cov_world_m2), np.linalg.inv(C)
        cov = np.linalg.inv(info_old + info_new)
        if rec.status != ACTIVE:  # graph landmarks take their position from the solver
            rec.xyz_world_m = cov @ (info_old @ rec.xyz_world_m + info_new @ l)
        rec.cov_world_m2 = 0.5 * (cov + cov.T)
        rec.size_sum_m += size
        rec.n_obs += 1
        rec.t_last = t

    def prune_candidates(self, t: float, oldest_kf: int) -> None:
        """Drop candidates unconfirmed for ``candidate_timeout_s`` and pending observations on
        keyframes older than ``oldest_kf`` (marginalized)."""
        for lid in [lid for lid, r in self.live.items() if r.status == CANDIDATE]:
            rec = self.live[lid]
            rec.pending = [o for o in rec.pending if o[0] >= oldest_kf]
            if t - rec.t_first > self.cfg.candidate_timeout_s or not rec.pending:
                self.drop(lid)

    def retire(self, lid: int) -> None:
        """Freeze a landmark that left the fixed-lag window; the oldest retired ones are dropped."""
        self.records[lid].status = RETIRED
        self.live.pop(lid, None)
        self._view = None
        self._retired.append(lid)
        while len(self._retired) > self.cfg.max_retired:
            self.records.pop(self._retired.pop(0), None)

    def drop(self, lid: int) -> None:
        """Forget a landmark entirely (a candidate that timed out, or one whose update failed)."""
        self.records.pop(lid, None)
        self.live.pop(lid, None)
        self._view = None

    def mapped(self) -> list[LandmarkRecord]:
        """Landmarks of the map (in the graph, or retired from it), in id order."""
        return [r for r in self.records.values() if r.status != CANDIDATE]


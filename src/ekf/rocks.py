"""The rock kind's EKF layer: the landmark update from one stereo rock frame.

Candidates (rock landmarks predicted within range) -> association (:mod:`reloc.association`,
joint compatibility with the full innovation covariance) -> the per-frame observation budget
(:mod:`reloc.budget`) -> one stacked Joseph update of the used pairs -> initialisation of new
landmarks with their cross covariances -> map hygiene (unconfirmed tentative landmarks dropped)
and the bound on the landmark count (the stalest landmarks marginalised out). The rock settings
are :class:`ekf.config.EkfConfig`'s own fields; see :mod:`ekf.kinds` for the seam.
"""

from __future__ import annotations

import math

import numpy as np

from ekf.config import EkfConfig
from ekf.errors import EkfInputError
from ekf.state import CALIB_DIM, FilterState
from ekf.updates import block_diag3, joseph_update
from reloc.association import associate
from reloc.backend import LandmarkMap, LandmarkUpdateReport
from reloc.budget import innovation_trace, select_observations
from reloc.geometry import skew
from reloc.kinds import LandmarkKind, kind_code
from reloc.landmark_model import (
    init_jacobians,
    point_in_base,
    point_jacobians,
    point_to_world,
)
from reloc.measurements import RockObservations
from reloc.persistence import persistence_agree, persistence_slack, place_agrees


def stacked_jacobian(H_head: np.ndarray, H_l: np.ndarray) -> np.ndarray:
    """Dense rows (3k, h + 3k) over ``[head (h), l_1, ..., l_k]`` for k point measurements."""
    k, _, h = H_head.shape
    Hc = np.zeros((3 * k, h + 3 * k))
    Hc[:, :h] = H_head.reshape(3 * k, h)
    for i in range(k):
        Hc[3 * i : 3 * i + 3, h + 3 * i : h + 3 * i + 3] = H_l
    return Hc


def joint_innovation_cov(P: np.ndarray, h: int, cols: np.ndarray, H_head: np.ndarray, H_l: np.ndarray) -> np.ndarray:
    """``H P H^T`` (3k, 3k) of k point measurements with rows :func:`stacked_jacobian` ``(H_head
    (k, 3, h), H_l (3, 3))`` over the head states ``[0, h)`` and the landmark columns ``cols``
    (3k,), without forming them: the landmark part of H is block-diagonal with one block, so it
    acts on 3-row slices (a frame of ~80 pairs: ~0.3 ms instead of the dense product's ~2 ms)."""
    k = H_head.shape[0]
    J = H_head.reshape(3 * k, h)
    B = (P[:h, cols].reshape(h, k, 3) @ H_l.T).reshape(h, 3 * k)  # P_hl (I x H_l)^T
    JB = J @ B
    L = (H_l @ P[np.ix_(cols, cols)].reshape(k, 3, 3 * k)).reshape(3 * k, k, 3) @ H_l.T  # (I x H_l) P_ll (I x H_l)^T
    return J @ P[:h, :h] @ J.T + JB + JB.T + L.reshape(3 * k, 3 * k)


def calibrated_measurements(s: FilterState, z: np.ndarray, Rz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rock measurements corrected by the nominal calibration: ``z' = E^T z / s`` (N, 3) and
    ``E^T Rz E / s^2`` (N, 3, 3); unchanged without calibration states."""
    if not s.calibrated:
        return z, Rz
    E, sc = s.calib_R, s.calib_s
    return (z @ E) / sc, np.einsum("ji,njk,kl->nil", E, Rz, E) / (sc * sc)


def calibration_jacobians(s: FilterState, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For corrected points ``q`` (N, 3) (predicted or measured, base_link): the Jacobian (N, 3, 4)
    of the corrected measurement ``z'`` w.r.t. ``[de, ds]`` (``z' ~ q + (ds/s) q - [q]x E^T de``),
    and the Jacobian (N, 3, 4) of a landmark initialised from ``z' = q`` (``l = p + R z'`` with
    ``q_true = z' - (ds/s) z' + [z']x E^T de``) before the rotation to world."""
    E, sc = s.calib_R, s.calib_s
    K = skew(q)  # (N, 3, 3)
    H = np.empty((q.shape[0], 3, CALIB_DIM))
    H[:, :, :3] = -K @ E.T
    H[:, :, 3] = q / sc
    return H, -H


def yaw_column(R_world_base: np.ndarray, p_lin: np.ndarray, l_lin: np.ndarray) -> np.ndarray:
    """(M, 3): the Jacobian of ``z = R^T (l - p)`` w.r.t. a yaw about world z, at the first
    estimates ``p_lin`` (3,), ``l_lin`` (M, 3): ``R^T [l - p]x e_z``. Only this column couples
    the unobservable yaw to the landmarks' lever arms; taking it at the first estimates keeps a
    yaw of the whole world unobservable (the other columns stay at the current estimate, which
    a first estimate decimetres off would spoil)."""
    d = np.asarray(l_lin, dtype=float).reshape(-1, 3) - np.asarray(p_lin, dtype=float)
    col = np.stack([d[:, 1], -d[:, 0], np.zeros(len(d))], axis=1)  # d x e_z
    return col @ R_world_base


class RockUpdate:
    """Stateless apart from its counters; operates on a :class:`FilterState` in place."""

    reserved = 0  # landmark slots of the bound on the state that other kinds may not take

    def __init__(self, config: EkfConfig, kind: LandmarkKind) -> None:
        self.config = config
        self.kind = kind.name
        self.code = kind_code(kind.name)
        self.counts = {"n_frames_skipped": 0, "n_associated": 0, "n_initialised": 0, "n_ambiguous": 0,
                       "n_jc_dropped": 0, "n_ambiguous_dropped": 0, "n_dropped_tentative": 0, "n_evicted": 0,
                       "n_forgotten": 0,
                       "n_budget_skipped": 0, "n_budget_new_skipped": 0, "n_lone_pairs_skipped": 0,
                       "n_not_persistent": 0, "n_first_sightings": 0}

    def _bump(self, count: bool, **kw: int) -> None:
        if count:
            for k, v in kw.items():
                self.counts[k] += int(v)

    def check(self, obs: RockObservations) -> None:
        """Finite, consistently shaped arrays (the filter checks the time order)."""
        arrays = (obs.xyz_base_m, obs.cov_base_m2, obs.size_m, obs.score)
        if not math.isfinite(obs.t) or not all(np.all(np.isfinite(a)) for a in arrays):
            raise EkfInputError(f"RockObservations at t={obs.t} contains NaN or inf")
        n = len(obs)
        if obs.xyz_base_m.shape != (n, 3) or obs.cov_base_m2.shape != (n, 3, 3) or obs.size_m.shape != (n,):
            raise EkfInputError("RockObservations arrays have inconsistent shapes")

    def landmark_map(self, s: FilterState) -> LandmarkMap:
        """Confirmed rock landmarks in world with marginal covariances (tentative ones are left out)."""
        rows = np.flatnonzero(s.book.confirmed & (s.book.kind == self.code))
        return LandmarkMap(
            ids=s.book.ids[rows].copy(),
            xyz_world_m=s.l_world[rows].copy(),
            cov_world_m2=s.landmark_cov_blocks(rows),
            size_m=s.book.size_m[rows],
            n_obs=s.book.n_obs[rows].copy(),
            kind=self.kind,
            catalog_row=s.book.catalog_row[rows].copy(),
        )

    def update(self, s: FilterState, obs: RockObservations, count: bool = True) -> LandmarkUpdateReport:
        """Process one frame in place; ``count`` False during replays (counters stay per input)."""
        cfg = self.config
        n_det = len(obs)
        if obs.t - s.t_last_frame.get(self.kind, -np.inf) < cfg.landmark_period_s - 1e-6:
            self._bump(count, n_frames_skipped=1)
            return LandmarkUpdateReport(obs.t, n_det, 0, 0, n_det)
        s.t_last_frame[self.kind] = obs.t
        s.reserved[self.code] = self.reserved  # this kind holds its share of the bound from its first frame
        z, Rz = calibrated_measurements(s, obs.xyz_base_m, obs.cov_base_m2 * cfg.rock_cov_scale)
        size = obs.size_m
        head = s.head

        cand = np.zeros(0, dtype=int)
        zhat = np.zeros((0, 3))
        if s.n_landmarks:
            zhat_all = point_in_base(s.R_world_base, s.p_world, s.l_world)
            limit = cfg.association.max_range_m + cfg.candidate_margin_m
            near = np.einsum("ij,ij->i", zhat_all, zhat_all) <= limit * limit
            cand = np.flatnonzero(near & (s.book.kind == self.code))  # rocks only
            zhat = zhat_all[cand]
        H_pose, H_l = point_jacobians(s.R_world_base, s.p_world, s.l_world[cand])
        if s.first_estimates:
            p_lin, l_lin = s.jacobian_points(cand)
            H_pose[:, :, 5] = yaw_column(s.R_world_base, p_lin, l_lin)
        if s.calibrated:
            # at the first estimates too: the range scale, like the world's yaw, is a direction
            # the landmarks alone cannot observe (scaling the map and the path about any point
            # with 1/s leaves every measurement as it is), and Jacobians at the moving estimate
            # made the filter "learn" a scale 20 sigma off its prior with no wheels at all
            q_cal = (l_lin - p_lin) @ s.R_world_base if s.first_estimates else zhat
            H_pose = np.concatenate([H_pose, calibration_jacobians(s, q_cal)[0]], axis=2)
        H_pose = s.pad_head(H_pose)
        S_hat = self._predicted_cov(s, cand, H_pose, H_l)

        def joint_cov(det: np.ndarray, ci: np.ndarray) -> np.ndarray:
            return joint_innovation_cov(s.P, head, s.landmark_cols(cand[ci]), H_pose[ci], H_l) + block_diag3(Rz[det])

        assoc = associate(z, Rz, zhat, S_hat, cfg.association, size, s.book.size_m[cand], joint_cov)
        det, ci = assoc.pairs
        a_cfg = cfg.association
        n_not_persistent = 0
        seen_det, seen_ids = det[:0], det[:0]
        if det.size and a_cfg.persistence_s > 0:  # clutter inside a gate: not seen there before
            xw, cw = point_to_world(s.R_world_base, s.p_world, z[det], Rz[det])
            seen_ids = s.book.ids[cand[ci]]
            seen_det = det
            slack, need = persistence_slack(a_cfg, z[det]), persistence_agree(a_cfg, S_hat[ci], Rz[det])
            ok = s.recent.test(seen_ids, obs.t, xw, cw, a_cfg.persistence_s, a_cfg.gate_chi2, slack, need)
            if a_cfg.persistence_any_detection:
                ok = place_agrees(ok, need, seen_ids, obs.t, xw, cw, s.recent, s.frames_for(self.code),
                                  a_cfg.persistence_s, a_cfg.gate_chi2, slack)
            n_not_persistent = int(det.size - ok.sum())
            det, ci = det[ok], ci[ok]
        n_lone = 0
        if cfg.skip_lone_ambiguous_pair and det.size == 1 and assoc.n_ambiguous > 0:
            det, ci, n_lone = det[:0], ci[:0], 1
        rows = cand[ci]
        if det.size:
            # every associated landmark counts as seen (confirmation, staleness); only the budget's
            # share enters the update
            s.book.observe(rows, obs.t, size[det])
            use = select_observations(s.book.confirmed[rows], innovation_trace(S_hat[ci], Rz[det]),
                                      cfg.budget.max_observations)
            u_det, u_ci = det[use], ci[use]
            idx = np.concatenate([np.arange(head), s.landmark_cols(cand[u_ci])])
            Hc = stacked_jacobian(H_pose[u_ci], H_l)
            nu = (z[u_det] - zhat[u_ci]).reshape(-1)
            s.P, res = joseph_update(s.P, idx, Hc, nu, block_diag3(Rz[u_det]))
            s.inject(res.dx)
            n_used = int(use.size)
        else:
            n_used = 0
        if seen_det.size:  # every associated detection, placed with the updated pose
            xw, cw = point_to_world(s.R_world_base, s.p_world, z[seen_det], Rz[seen_det])
            s.recent.record(seen_ids, obs.t, xw, cw)
        if n_det and a_cfg.persistence_s > 0 and a_cfg.persistence_any_detection:  # every detection, by place
            s.frames_for(self.code).record(obs.t, *point_to_world(s.R_world_base, s.p_world, z, Rz),
                                           a_cfg.persistence_s)

        # a new landmark only from a second sighting at the same place (first sightings wait)
        new = np.flatnonzero(assoc.is_new)
        n_first = 0
        if new.size and a_cfg.persistence_s > 0:
            xw, cw = point_to_world(s.R_world_base, s.p_world, z[new], Rz[new])
            again = s.pending_for(self.code).confirm(obs.t, xw, cw, a_cfg.persistence_s, a_cfg.gate_chi2,
                                                     persistence_slack(a_cfg, z[new]))
            n_first = int(new.size - again.sum())
            new = new[again]
        # hygiene and the bound first, so the state never exceeds max_landmarks
        stale = s.book.stale(obs.t)
        protect = stale.copy()
        protect[rows] = True
        dist = np.linalg.norm(s.l_world - s.p_world, axis=1)
        far = np.zeros_like(stale)
        if cfg.forget_distance_m > 0:  # out of reach: marginalised whatever the count
            far = (np.linalg.norm(s.l_world[:, :2] - s.p_world[:2], axis=1) > cfg.forget_distance_m) & ~protect
        evict = self._evictions(s, obs.t, new.size, stale | far, protect, dist)
        s.keep_landmarks(~(stale | far | evict))
        room = self._room(s)
        n_new = min(new.size, room)  # what the bound on the state admits ...
        if cfg.budget.max_new > 0:  # ... and the budget
            room = min(room, cfg.budget.max_new)
        new = new[np.argsort(np.linalg.norm(z[new], axis=1), kind="stable")][:room]  # nearest first
        if new.size:
            l_new, cov_w = point_to_world(s.R_world_base, s.p_world, z[new], Rz[new])
            G_pose, _ = init_jacobians(s.R_world_base, z[new])
            if s.calibrated:
                G_cal = np.einsum("ij,njk->nik", s.R_world_base, calibration_jacobians(s, z[new])[1])
                G_pose = np.concatenate([G_pose, G_cal], axis=2)
            G_pose = s.pad_head(G_pose)
            s.append_landmarks(l_new, G_pose, cov_w)
            new_ids = s.book.add(obs.t, size[new], self.code, n_obs=2 if a_cfg.persistence_s > 0 else 1)
            if a_cfg.persistence_s > 0:
                s.recent.record(new_ids, obs.t, l_new, cov_w)
        self._bump(count, n_associated=det.size, n_initialised=new.size, n_ambiguous=assoc.n_ambiguous,
                   n_jc_dropped=assoc.n_jc_dropped, n_ambiguous_dropped=assoc.n_ambiguous_dropped,
                   n_dropped_tentative=stale.sum(), n_evicted=evict.sum(), n_forgotten=far.sum(),
                   n_budget_skipped=det.size - n_used, n_budget_new_skipped=n_new - new.size,
                   n_lone_pairs_skipped=n_lone, n_not_persistent=n_not_persistent,
                   n_first_sightings=n_first)
        return LandmarkUpdateReport(obs.t, n_det, n_used, int(new.size), n_det - n_used - int(new.size))

    def _counts(self, s: FilterState, keep: np.ndarray | None = None) -> dict[int, int]:
        """Landmarks per kind code that holds a reserve (of the rows in ``keep`` (N,), all for None)."""
        kinds = s.book.kind if keep is None else s.book.kind[keep]
        return {code: int(np.count_nonzero(kinds == code)) for code in s.reserved}

    def _held_by_others(self, s: FilterState, counts: dict[int, int]) -> int:
        """Slots the other kinds' reserves hold empty."""
        return sum(max(n - counts[code], 0) for code, n in s.reserved.items() if code != self.code)

    def _room(self, s: FilterState) -> int:
        """New landmarks of this kind the bound on the state admits now."""
        return max(self.config.max_landmarks - s.n_landmarks - self._held_by_others(s, self._counts(s)), 0)

    def _evictions(self, s: FilterState, t: float, n_new: int, gone: np.ndarray, protect: np.ndarray,
                   dist: np.ndarray) -> np.ndarray:
        """(N,) bool: the landmarks marginalised to make room for ``n_new`` new ones at ``t``
        (``gone`` (N,) leave anyway). Not one seen within ``keep_seen_s`` (a landmark still in
        view is not swapped for a new one), nor, of another kind, one of that kind's reserved
        share; but new landmarks within this kind's own reserved share take their slots from the
        other kinds' landmarks beyond theirs, seen recently or not."""
        counts = self._counts(s, ~gone)
        need = s.n_landmarks - int(gone.sum()) + n_new + self._held_by_others(s, counts) - self.config.max_landmarks
        if need <= 0:
            return np.zeros(s.n_landmarks, dtype=bool)
        surplus = {code: max(counts[code] - n, 0) for code, n in s.reserved.items() if code != self.code}
        recent = t - s.book.t_last < self.config.keep_seen_s
        evict = s.book.evictions(need, dist, protect | gone | recent, surplus)
        short = need - int(evict.sum())
        claim = min(n_new, max(self.reserved - counts[self.code], 0))
        if short > 0 and claim > 0:
            taken = self._counts(s, evict)
            left = {code: n - taken[code] for code, n in surplus.items()}
            own = s.book.kind == self.code
            evict |= s.book.evictions(min(short, claim), dist, protect | gone | evict | own, left)
        return evict

    @staticmethod
    def _predicted_cov(s: FilterState, cand: np.ndarray, H_pose: np.ndarray, H_l: np.ndarray) -> np.ndarray:
        """``H P H^T`` (M, 3, 3) of each candidate's predicted measurement (head + landmark blocks)."""
        if cand.size == 0:
            return np.zeros((0, 3, 3))
        Ppp = s.P[: s.head, : s.head]
        Ppl = s.head_landmark_cov(cand)  # (M, head, 3)
        Pll = s.landmark_cov_blocks(cand)  # (M, 3, 3)
        A = np.einsum("mij,jk,mlk->mil", H_pose, Ppp, H_pose)
        C = np.einsum("mij,mjk,lk->mil", H_pose, Ppl, H_l)
        D = np.einsum("ij,mjk,lk->mil", H_l, Pll, H_l)
        S = A + C + np.transpose(C, (0, 2, 1)) + D
        return 0.5 * (S + np.transpose(S, (0, 2, 1)))

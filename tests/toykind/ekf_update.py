"""The cairn kind's EKF update (toy kind): nearest-Mahalanobis association of each cairn with the
cairn landmarks, a Joseph update per associated cairn, new cairns initialised with their cross
covariances. Runs again, unchanged, when the filter replays its history after a late fix."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ekf.errors import EkfInputError
from ekf.kinds import kind_config
from ekf.updates import joseph_update
from reloc.backend import LandmarkMap, LandmarkUpdateReport
from reloc.kinds import kind_code
from reloc.landmark_model import init_jacobians, point_in_base, point_jacobians, point_to_world


@dataclass(frozen=True)
class CairnEkfConfig:
    gate_chi2: float = 11.34  # 3 dof, 99 %
    cov_scale: float = 1.0


class CairnUpdate:
    config_class = CairnEkfConfig

    def __init__(self, config, kind) -> None:
        self.cfg = kind_config(type(self), kind, config)
        self.kind, self.code = kind.name, kind_code(kind.name)
        self.counts = {"n_cairns_associated": 0, "n_cairns_new": 0}

    def check(self, obs) -> None:
        if not np.isfinite(obs.xyz_base_m).all():
            raise EkfInputError(f"CairnObservations at t={obs.t} contains NaN")

    def _pad(self, s, H6: np.ndarray) -> np.ndarray:
        """(..., 3, 6) pose Jacobians -> (..., 3, head): cairns see no calibration."""
        out = np.zeros(H6.shape[:-1] + (s.head,))
        out[..., :6] = H6
        return out

    def update(self, s, obs, count: bool = True) -> LandmarkUpdateReport:
        n, n_assoc, new = len(obs), 0, []
        Rz = obs.cov_base_m2 * self.cfg.cov_scale
        for i in range(n):
            rows = np.flatnonzero(s.book.kind == self.code)
            best = None
            for r in rows:
                zhat = point_in_base(s.R_world_base, s.p_world, s.l_world[r])[0]
                Hp, Hl = point_jacobians(s.R_world_base, s.p_world, s.l_world[r])
                idx = np.concatenate([np.arange(s.head), s.landmark_cols([r])])
                Hc = np.hstack([self._pad(s, Hp[0]), Hl])
                nu = obs.xyz_base_m[i] - zhat
                S = Hc @ s.P[np.ix_(idx, idx)] @ Hc.T + Rz[i]
                d2 = float(nu @ np.linalg.solve(S, nu))
                if d2 <= self.cfg.gate_chi2 and (best is None or d2 < best[0]):
                    best = (d2, r, idx, Hc, nu)
            if best is None:
                new.append(i)
                continue
            _, r, idx, Hc, nu = best
            s.P, res = joseph_update(s.P, idx, Hc, nu, Rz[i])
            s.inject(res.dx)
            s.book.observe(np.array([r]), obs.t, obs.size_m[i:i + 1])
            n_assoc += 1
        if new:
            new = np.array(new)
            l_new, cov_w = point_to_world(s.R_world_base, s.p_world, obs.xyz_base_m[new], Rz[new])
            G_pose, _ = init_jacobians(s.R_world_base, obs.xyz_base_m[new])
            s.append_landmarks(l_new, self._pad(s, G_pose), cov_w)
            s.book.add(obs.t, obs.size_m[new], self.code)
        if count:
            self.counts["n_cairns_associated"] += n_assoc
            self.counts["n_cairns_new"] += len(new)
        return LandmarkUpdateReport(obs.t, n, n_assoc, len(new), 0)

    def landmark_map(self, s) -> LandmarkMap:
        rows = np.flatnonzero(s.book.confirmed & (s.book.kind == self.code))
        return LandmarkMap(s.book.ids[rows].copy(), s.l_world[rows].copy(), s.landmark_cov_blocks(rows),
                           s.book.size_m[rows], s.book.n_obs[rows].copy(), self.kind)

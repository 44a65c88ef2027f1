"""The cairn kind's smoother layer (toy kind): cairns as Point3 variables ``K(j)`` (key symbol
``k``), one bearing-range factor per cairn and keyframe, nearest-neighbour association in world,
and the frozen estimate of a cairn that leaves the fixed-lag window."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from fgslam.smoother.factors import make_point_factor
from fgslam.smoother.kinds import POINT3, kind_config
from reloc.backend import LandmarkMap, LandmarkUpdateReport


@dataclass(frozen=True)
class CairnSmootherConfig:
    gate_m: float = 1.0  # a detection within this of a cairn's estimate is that cairn
    huber_k: float = 3.0


class CairnLandmarks:
    variable = POINT3
    config_class = CairnSmootherConfig

    def __init__(self, config, kind, calib_key) -> None:
        self.cfg = kind_config(type(self), kind, config)
        self.kind, self.symbol = kind.name, kind.symbol
        self.records: dict[int, dict] = {}
        self.n_frames = 0
        self.n_marginalized = 0
        self._buf: set[int] = set()
        self._seen: set[int] = set()

    def key(self, j: int) -> int:
        return gtsam.symbol(self.symbol, j)

    def observe(self, obs, frame) -> LandmarkUpdateReport:
        self.n_frames += 1
        T_now = frame.T_world_kf @ frame.T_kf_now
        world = obs.xyz_base_m @ T_now[:3, :3].T + T_now[:3, 3]
        R_rel, t_rel = frame.T_kf_now[:3, :3], frame.T_kf_now[:3, 3]
        n_assoc = n_new = 0
        for i in range(len(obs)):
            z_kf = R_rel @ obs.xyz_base_m[i] + t_rel
            R_kf = R_rel @ obs.cov_base_m2[i] @ R_rel.T + np.eye(3) * 1e-4  # + the odometry since the keyframe
            live = [(j, r) for j, r in self.records.items() if not r["retired"]]
            d = [np.linalg.norm(r["xyz"][:2] - world[i, :2]) for _, r in live]
            if d and min(d) <= self.cfg.gate_m:
                j, rec = live[int(np.argmin(d))]
                rec["n_obs"] += 1
                rec["size_sum"] += float(obs.size_m[i])
                rec["t_last"] = obs.t
                n_assoc += 1
            else:
                j = max(self.records, default=-1) + 1
                cov_w = T_now[:3, :3] @ obs.cov_base_m2[i] @ T_now[:3, :3].T
                self.records[j] = {"xyz": world[i].copy(), "cov": cov_w, "n_obs": 1, "size_sum": float(obs.size_m[i]),
                                   "retired": False, "t_last": obs.t}
                frame.values.insert(self.key(j), world[i].copy())
                n_new += 1
            if j in self._seen:
                continue
            self._seen.add(j)
            self._buf.add(j)
            frame.graph.add(make_point_factor(gtsam.symbol("x", frame.kf), self.key(j), z_kf, R_kf, self.cfg.huber_k))
        return LandmarkUpdateReport(obs.t, len(obs), n_assoc, n_new, 0)

    def buffered_stamps(self, t: float) -> dict[int, float]:
        return {self.key(j): t for j in self._buf}

    def on_keyframe(self) -> None:
        self._buf, self._seen = set(), set()

    def drop(self, index: int) -> None:
        self.records.pop(index, None)

    def marginalize(self, index: int, solver) -> None:
        rec = self.records[index]
        rec["xyz"], rec["retired"] = solver.estimate(self.key(index)), True
        self.n_marginalized += 1

    def prune(self, t: float, oldest_kf: int) -> None:
        return None

    def refresh(self, T_world_kf, solver) -> None:
        for j, rec in self.records.items():
            if not rec["retired"] and solver.alive(self.key(j)):
                rec["xyz"] = solver.estimate(self.key(j))

    @property
    def n_landmarks(self) -> int:
        return len(self.records)

    def landmark_map(self, pose_cov_at) -> LandmarkMap:
        ids = np.array(sorted(self.records), dtype=int)
        recs = [self.records[j] for j in ids]
        # the map is in the world: the cairn's own covariance plus the drift of the pose that last saw it
        cov = np.array([r["cov"] for r in recs]).reshape(-1, 3, 3) + pose_cov_at(np.array([r["t_last"] for r in recs]))
        return LandmarkMap(ids, np.array([r["xyz"] for r in recs]).reshape(-1, 3), cov,
                           np.array([r["size_sum"] / r["n_obs"] for r in recs]),
                           np.array([r["n_obs"] for r in recs], dtype=int), self.kind)

    def stats(self) -> dict:
        return {"n_cairns_marginalized": self.n_marginalized}

"""The cairn kind's relocalizer and catalog (toy kind): nearest-neighbour pairs of the cairn map
(in the estimated world) with the cairn catalog, a rigid 2D fit, and the fix it gives the rover."""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.io.catalog_csv import CatalogFile
from fgslam.match_to_fix import fix_from_similarity
from fgslam.relocalizer import FixAttempt, RelocalizerConfig
from reloc.config import config_from_dict
from reloc.procrustes import umeyama_2d


@dataclass(frozen=True)
class CairnCatalog:
    xy_m: np.ndarray  # (N, 2) world
    size_m: np.ndarray  # (N,) heights

    def __len__(self) -> int:
        return len(self.xy_m)


def read_cairn_csv(path: Path) -> CairnCatalog:
    rows = list(csv.DictReader(Path(path).read_text().splitlines()))
    return CairnCatalog(np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2),
                        np.array([float(r["size"]) for r in rows]))


def write_cairn_csv(path: Path, cat: CairnCatalog) -> None:
    lines = ["x,y,size"] + [f"{x:.6f},{y:.6f},{s:.6f}" for (x, y), s in zip(cat.xy_m, cat.size_m)]
    Path(path).write_text("\n".join(lines) + "\n")


CAIRN_CATALOG_FILE = CatalogFile("cairns.csv", read_cairn_csv)


@dataclass(frozen=True)
class CairnRelocalizerConfig:
    period_s: float = 5.0
    gate_m: float = 1.5
    delay_s: float = 1.0
    min_pairs: int = 3


class CairnRelocalizer:
    def __init__(self, catalog: CairnCatalog, config=None) -> None:
        self.config = config if isinstance(config, CairnRelocalizerConfig) else \
            config_from_dict(CairnRelocalizerConfig, config, where="cairns relocalizer.")
        self.catalog = catalog
        self.kinds = ("cairns",)
        self.period_s = self.config.period_s
        self.build_time_s = 0.0
        self._fix_cfg = RelocalizerConfig()

    def wants(self, est) -> bool:
        return True

    def attempt(self, maps, est) -> FixAttempt:
        cfg, lmap = self.config, maps["cairns"]
        t0 = time.perf_counter()
        local = lmap.xyz_world_m[:, :2]
        pairs = []
        for i, xy in enumerate(local):
            d = np.linalg.norm(self.catalog.xy_m - xy, axis=1)
            if d.size and d.min() <= cfg.gate_m:
                pairs.append((i, int(np.argmin(d))))
        if len(pairs) < cfg.min_pairs:
            return FixAttempt(est.t, len(lmap), "too few landmarks", time.perf_counter() - t0, source="cairns")
        p = np.array(pairs)
        L, W = local[p[:, 0]], self.catalog.xy_m[p[:, 1]]
        sim = umeyama_2d(L, W, with_scale=False)
        rmse = float(np.sqrt(np.mean(np.sum((sim.apply(L) - W) ** 2, axis=1))))
        fix = fix_from_similarity(est, float(sim.theta_rad), np.asarray(sim.translation), 1.0, L, rmse, self._fix_cfg,
                                  t_recv=est.t + cfg.delay_s)
        return FixAttempt(est.t, len(lmap), "fix", time.perf_counter() - t0, fix, L, W,
                          np.array([est.position_m[0], est.position_m[1], est.yaw_rad]), source="cairns")

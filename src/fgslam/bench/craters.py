"""Craters in the loop, measured on ``fgslam sim`` directories of the kilometre presets.

For each directory, passes of one back-end (iSAM2 by default) over the same bag, each as ``fgslam
run DIR`` runs it with the same config (the directory's ``backend.yaml``, or ``--config``: the
back-end's overrides, the runner's and every relocalizer's settings, fix heights from a terrain
model; :class:`fgslam.run_setup.RunSetup`) but for the kinds the pass names:

- ``no fixes``: rocks and craters mapped, no relocalization (the drift);
- ``rocks alone``: crater frames left out (``kinds.craters.use`` False), rock fixes;
- ``craters alone``: rocks and craters mapped, fixes from the crater relocalizer only;
- ``rocks + craters``: both mapped, fixes from both relocalizers.

Per pass: the ATE (RMSE, m) and the fixes. For every crater-relocalizer attempt the bench also
counts the *catalogued craters mapped*: crater landmarks that, moved into the true frame by the
difference between the estimate and the truth at the attempt, lie within ``mapped_gate_m`` of a
catalog crater of a diameter within ratio 1.5 (the map itself is never corrected). An attempt
with at least ``min_catalogued`` of them *should* relocalize; it succeeds when it gives a fix
within ``wrong_fix_m`` of the truth. A fix farther than that (any attempt) is a wrong fix.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.fix_sources import WrappedProducer
from fgslam.metrics import fix_errors, interpolate_truth

PASSES: dict[str, tuple[bool, tuple[str, ...]]] = {  # name -> (craters mapped, relocalizers)
    "no fixes": (True, ()),
    "rocks alone": (False, ("rocks",)),
    "craters alone": (True, ("craters",)),
    "rocks + craters": (True, ("rocks", "craters")),
}


@dataclass(frozen=True)
class CraterBenchConfig:
    backend: str = "isam2"
    passes: tuple[str, ...] = tuple(PASSES)
    wrong_fix_m: float = 1.5  # a fix this far from the truth is wrong (craters are metres apart)
    mapped_gate_m: float = 1.5
    min_catalogued: int = 6
    duration_s: float | None = None  # the stretch: the first this many seconds of each bag (None: all)


class _CountingRelocalizer(WrappedProducer):
    """A relocalizer that also counts, at each attempt, the catalogued craters mapped (module doc);
    its period (with the inner one's backoff), kinds and config are the inner relocalizer's."""

    def __init__(self, inner, catalog, gt, cfg: CraterBenchConfig) -> None:
        super().__init__(inner)
        self.catalog, self.gt, self.cfg = catalog, gt, cfg
        self.records: list[tuple[float, int, object]] = []  # (t, catalogued mapped, attempt)

    def catalogued(self, lmap, est) -> int:
        if len(lmap) == 0:
            return 0
        p_gt, yaw_gt, _ = interpolate_truth(self.gt, np.array([est.t]))
        dyaw = float(yaw_gt[0] - est.yaw_rad)
        c, s = np.cos(dyaw), np.sin(dyaw)
        xy = (lmap.xyz_world_m[:, :2] - est.position_m[:2]) @ np.array([[c, s], [-s, c]]) + p_gt[0, :2]
        d = np.linalg.norm(xy[:, None, :] - self.catalog.xy_m[None], axis=2)
        ratio = np.maximum(lmap.size_m[:, None], self.catalog.size_m[None]) / np.minimum(lmap.size_m[:, None],
                                                                                           self.catalog.size_m[None])
        near = self.inner.config.max_radius_m >= np.linalg.norm(lmap.xyz_world_m[:, :2] - est.position_m[:2], axis=1)
        ok = np.any((d <= self.cfg.mapped_gate_m) & (ratio <= 1.5), axis=1) & near & (lmap.n_obs >= self.inner.config.min_obs)
        return int(ok.sum())

    def attempt(self, maps, est):
        n = self.catalogued(maps["craters"], est)
        att = self.inner.attempt(maps, est)
        self.records.append((est.t, n, att))
        return att


def bench_directory(directory: Path, cfg: CraterBenchConfig, progress: Callable[[str], None] | None = None,
                    config: Path | None = None) -> dict:
    """Every pass of ``cfg`` on the ``fgslam sim`` directory (see module doc), each as ``fgslam run
    DIR --config CONFIG`` makes it (None: the directory's ``backend.yaml``) but for the pass's
    kinds: a JSON-ready dict."""
    from fgslam.fix_sources import OnlineFixes
    from fgslam.metrics import ate
    from fgslam.run_setup import RunSetup

    directory = Path(directory)
    setup = RunSetup.of_directory(directory, config, cfg.duration_s)
    inputs, gt = setup.inputs, setup.gt
    out: dict = {"directory": str(directory), "duration_s": cfg.duration_s, "catalog_craters": len(inputs.catalogs.get("craters", ())),
                 "catalog_rocks": len(inputs.catalogs["rocks"]), "passes": {}}
    for name in cfg.passes:
        craters_used, relocs = PASSES[name]
        if progress is not None:
            progress(f"{directory.name}: {name}")
        producers = setup.relocalizers(relocs)
        counted = None
        for i, r in enumerate(producers):
            if r.kinds == ("craters",):
                counted = producers[i] = _CountingRelocalizer(r, inputs.catalogs["craters"], gt, cfg)
        be = setup.backend(cfg.backend, None if craters_used else {"kinds": {"craters": {"use": False}}})
        res = setup.run(be, OnlineFixes(producers) if producers else None)
        row: dict = {"ate_rmse_m": ate(res.final, gt).rmse, "wall_s": res.wall_s,
                     "landmarks": {k: len(m) for k, m in res.landmarks.items()}}
        accepted = {(o.fix.t_meas, o.fix.t_recv) for o in res.outcomes if o.accepted}
        by_source: dict = {}
        for att in res.attempts:
            b = by_source.setdefault(att.source, {"attempts": 0, "fixes": 0, "accepted": 0, "wrong": 0, "errors_m": [],
                                                  "statuses": Counter()})
            b["attempts"] += 1
            b["statuses"][att.status] += 1  # why the others gave no fix
            if att.fix is not None:
                err = float(fix_errors(np.array([att.fix.xyyaw]), np.array([att.fix.t_meas]), gt)[0][0])
                b["fixes"] += 1
                b["accepted"] += int((att.fix.t_meas, att.fix.t_recv) in accepted)
                b["wrong"] += int(err > cfg.wrong_fix_m)
                b["errors_m"].append(err)
        for b in by_source.values():
            e = b.pop("errors_m")
            b["median_error_m"] = float(np.median(e)) if e else None
            b["statuses"] = dict(b["statuses"])
        row["fixes"] = by_source
        if counted is not None:
            should = [(t, n, a) for t, n, a in counted.records if n >= cfg.min_catalogued]
            ok = 0
            failed: Counter[str] = Counter()  # why the attempts that should have relocalized did not
            for _, _, a in should:
                good = False
                if a.fix is not None:
                    err = float(fix_errors(np.array([a.fix.xyyaw]), np.array([a.fix.t_meas]), gt)[0][0])
                    good = err <= cfg.wrong_fix_m
                ok += int(good)
                if not good:
                    failed["wrong fix" if a.fix is not None else a.status] += 1
            row["crater_reloc"] = {
                "attempts": len(counted.records), "with_min_catalogued": len(should), "succeeded": ok,
                "success_rate": ok / len(should) if should else None, "failed_by_status": dict(failed),
                "statuses": dict(Counter(a.status for _, _, a in counted.records)),
                "median_catalogued_mapped": float(np.median([n for _, n, _ in counted.records])) if counted.records else 0.0,
            }
        out["passes"][name] = row
    return out


def summary_rows(results: list[dict]) -> tuple[list[str], list[list[str]]]:
    """One table row per (directory, pass)."""
    cols = ["directory", "pass", "ATE m", "fixes (rocks)", "wrong (rocks)", "fixes (craters)", "wrong (craters)",
            "crater attempts >= N catalogued", "success", "wall s"]
    rows = []
    for r in results:
        for name, p in r["passes"].items():
            fr, fc = p["fixes"].get("rocks", {}), p["fixes"].get("craters", {})
            cr = p.get("crater_reloc")
            rows.append([Path(r["directory"]).name, name, f"{p['ate_rmse_m']:.3f}", str(fr.get("fixes", "-")),
                         str(fr.get("wrong", "-")), str(fc.get("fixes", "-")), str(fc.get("wrong", "-")),
                         f"{cr['with_min_catalogued']}/{cr['attempts']}" if cr else "-",
                         "-" if not cr or cr["success_rate"] is None else f"{cr['succeeded']} ({100 * cr['success_rate']:.1f} %)",
                         f"{p['wall_s']:.0f}"])
    return cols, rows


__all__ = ["PASSES", "CraterBenchConfig", "bench_directory", "summary_rows"]

"""False fixes on out-of-catalog maps: how often a relocalizer accepts a match for a map whose
landmarks are not in the catalog under it, against the bound its acceptance test claims.

``python -m fgslam.bench.false_fixes DIR [--config backend.yaml] [--backend ekf]
[--duration-s S] [--kinds rocks,craters] [--out results.json]``: one pass of BACKEND without fixes over the
``fgslam sim`` directory DIR (the first S seconds). At every attempt of each kind's relocalizer,
its local map (the back-end's map with the relocalizer's window of the recent path) and the
estimate are moved, together, by the offset from the rover's true position now to the latest true
position of its past that is at least twice the map's extent plus the search radius away: the map
then lies over catalogued ground the rover drove through, with the catalog's real density, sizes
and false entries, but none of its landmarks is there (the attempt is skipped while the rover has
not yet been that far). Every fix from such an attempt is false. The same attempt is also made on the
map where it is, so the table shows the success rate beside the false-fix rate. An estimate
that the relocalizer would search the whole catalog for (lost: planar sigma above
``lost_sigma_m``, or no search prior) is not probed away: the whole catalog holds the map's own
place, wherever the map is moved (skipped as "whole-catalog search").

The acceptance test bounds the chance that a wrong pose is accepted by
``10 ** matcher.max_log10_false_alarm`` per attempt (docs/matcher.md); the measured rate is
reported with its 95 % Clopper-Pearson upper bound.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from fgslam.backends.reanchor import is_lost
from fgslam.local_window import LocalMapWindow
from fgslam.relocalizer import FixAttempt, StaleMapCheck
from reloc.backend import LandmarkMap, PoseEstimate, Trajectory

log = logging.getLogger(__name__)


def shifted(lmap: LandmarkMap, est: PoseEstimate, dxy: np.ndarray) -> tuple[LandmarkMap, PoseEstimate]:
    """``lmap`` and ``est`` moved by ``dxy`` (2,) in the world plane."""
    d3 = np.array([dxy[0], dxy[1], 0.0])
    T = est.T_world_base.copy()
    T[:3, 3] += d3
    return dataclasses.replace(lmap, xyz_world_m=lmap.xyz_world_m + d3), dataclasses.replace(est, T_world_base=T)


class OutOfCatalogProbe:
    """A fix producer for one landmark kind that never gives the back-end a fix: at each attempt
    it matches the windowed map where it is (``home``) and moved to a place of its past far enough
    for none of the map to be there (``away``), and records both attempts."""

    def __init__(self, kind: str, catalog, config, truth: Trajectory) -> None:
        from fgslam.fix_sources import relocalizers_for

        self.kinds = (kind,)
        self.period_s = config.period_s
        self.config = config
        self.window = LocalMapWindow(config.window_path_m, config.window_max_kept) if config.window_path_m > 0 else None
        bare = dataclasses.replace(config, window_path_m=0.0, min_new_observations=0)
        # two matchers: successive "home" attempts share rocks (correlation bookkeeping), "away" ones do not
        self.home, self.away = (relocalizers_for({kind: catalog}, {kind: bare})[0] for _ in range(2))
        self.truth_t = np.asarray(truth.t)
        self.truth_xy = np.asarray(truth.T_world_base)[:, :2, 3]
        step = max(1, int(len(self.truth_t) / max(self.truth_t[-1] - self.truth_t[0], 1e-9)))  # ~1 Hz for the search
        self._past_t, self._past_xy = self.truth_t[::step], self.truth_xy[::step]
        self.records: list[dict] = []
        self._fresh = StaleMapCheck(config.min_new_observations)  # as the relocalizer checks its map

    def wants(self, est: PoseEstimate) -> bool:
        return self.home.wants(est)

    def _true_xy(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.truth_t, self.truth_xy[:, i]) for i in (0, 1)])

    def attempt(self, maps: Mapping[str, LandmarkMap], est: PoseEstimate) -> FixAttempt:
        kind = self.kinds[0]
        lmap = maps[kind]
        rec: dict = {"t": float(est.t), "kind": kind}
        if self._fresh.stale(lmap):
            rec["skipped"] = "stale map"
            self.records.append(rec)
            return FixAttempt(est.t, len(lmap), "stale map", 0.0, source=kind)
        if self.window is not None:
            lmap = self.window.update(lmap, est.position_m)
        home = self.home.attempt({kind: lmap}, est)
        rec.update(home=home.status, home_error_m=self._error(home, est.t))
        rec["sigma_m"] = float(est.planar_sigma_m)
        whole_catalog = self.config.prior_sigmas is None or is_lost(est, self.config.lost_sigma_m)
        dxy = None if whole_catalog else self._away_offset(lmap, est)
        if whole_catalog:
            # no search prior: the whole catalog is searched, the map's own place included,
            # so moving the map does not take it out of the catalog
            rec["skipped"] = "whole-catalog search (lost or no prior)"
        elif dxy is None:
            rec["skipped"] = "no place far enough yet"
        else:
            m2, e2 = shifted(lmap, est, dxy)
            away = self.away.attempt({kind: m2}, e2)
            rec.update(away=away.status, away_shift_m=float(np.hypot(*dxy)),
                       away_inliers=None if away.fix is None else len(away.local_xy),
                       away_from_home_m=self._error(away, est.t))
        self.records.append(rec)
        return FixAttempt(est.t, len(lmap), f"probe: {home.status}", home.match_time_s, source=kind)

    def _away_offset(self, lmap: LandmarkMap, est: PoseEstimate) -> np.ndarray | None:
        """Offset from the rover's true position to the latest true position of its past that is
        at least twice the map's extent plus the search radius away (None: none yet)."""
        if len(lmap) == 0:
            return None
        extent = float(np.max(np.linalg.norm(lmap.xyz_world_m[:, :2] - est.position_m[:2], axis=1)))
        sigma = est.planar_sigma_m
        reach = 2.0 * extent + self.config.prior_min_radius_m + (self.config.prior_sigmas or 0.0) * sigma
        now = self._true_xy(est.t)
        past = self._past_t < est.t
        far = np.flatnonzero(np.linalg.norm(self._past_xy[past] - now, axis=1) >= reach)
        return None if far.size == 0 else self._past_xy[past][far[-1]] - now

    def _error(self, att: FixAttempt, t: float) -> float | None:
        if att.fix is None:
            return None
        return float(np.hypot(*(np.array([att.fix.x_m, att.fix.y_m]) - self._true_xy(t))))


def clopper_pearson_upper(k: int, n: int, level: float = 0.95) -> float:
    """One-sided upper ``level`` confidence bound of a binomial rate with ``k`` events in ``n``."""
    from scipy.stats import beta

    if n == 0:
        return float("nan")
    return 1.0 if k >= n else float(beta.ppf(level, k + 1, n - k))


def summarize(records: list[dict], bound: Mapping[str, float]) -> dict:
    """Per kind: home attempts and fixes (with their median error), away attempts, false fixes,
    the measured false-fix rate with its upper bound, and the acceptance test's bound."""
    out: dict = {}
    for kind in sorted({r["kind"] for r in records}):
        rs = [r for r in records if r["kind"] == kind]
        home = [r for r in rs if "home" in r]
        errs = [r["home_error_m"] for r in home if r.get("home_error_m") is not None]
        away = [r for r in rs if "away" in r]
        false = sum(1 for r in away if r["away"] == "fix")
        out[kind] = {
            "attempts": len(home), "fixes": len(errs),
            "fix_error_median_m": float(np.median(errs)) if errs else None,
            "fix_error_p90_m": float(np.percentile(errs, 90)) if errs else None,
            "fix_error_max_m": float(np.max(errs)) if errs else None,
            "fixes_over_1m": sum(1 for e in errs if e > 1.0),
            "fixes_over_5m": sum(1 for e in errs if e > 5.0),
            "out_of_catalog_attempts": len(away),
            "out_of_catalog_tried": sum(1 for r in away if r["away"] not in ("too few landmarks",)),
            "false_fixes": false,
            "false_fix_rate": false / len(away) if away else None,
            "false_fix_rate_upper95": clopper_pearson_upper(false, len(away)),
            "bound_per_attempt": bound.get(kind),
            "skipped": {s: sum(1 for r in rs if r.get("skipped") == s) for s in sorted({r.get("skipped") for r in rs} - {None})},
        }
    return out


def main(argv: list[str] | None = None) -> dict:
    from fgslam.fix_sources import OnlineFixes
    from fgslam.run_setup import RunSetup
    from reloc.config import config_from_dict
    from reloc.matcher import MatcherConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--config", type=Path)
    ap.add_argument("--backend", default="ekf")
    ap.add_argument("--duration-s", type=float)
    ap.add_argument("--kinds", help="comma-separated landmark kinds to probe (default: every kind with a catalog)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    setup = RunSetup.of_directory(args.directory, args.config, args.duration_s)
    gt = setup.gt
    if gt is None:
        raise SystemExit(f"{args.directory}: no ground truth in the bag: out-of-catalog places come from it")
    probes, bound = [], {}
    relocs = setup.relocalizers()
    wanted = {r.kinds[0] for r in relocs} if args.kinds is None else set(args.kinds.split(","))
    unknown = wanted - {r.kinds[0] for r in relocs}
    if unknown:
        ap.error(f"--kinds {sorted(unknown)}: {args.directory} has catalogs of {sorted(r.kinds[0] for r in relocs)} only")
    for r in relocs:
        kind = r.kinds[0]
        if kind not in wanted:
            continue
        probes.append(OutOfCatalogProbe(kind, setup.inputs.catalogs[kind], r.config, gt))
        mcfg = config_from_dict(MatcherConfig, dict(r.config.matcher or {}), where="matcher.")
        bound[kind] = 10.0 ** mcfg.max_log10_false_alarm
    setup.run(setup.backend(args.backend), OnlineFixes(probes))
    records = [rec for p in probes for rec in p.records]
    res = {"directory": str(args.directory), "backend": args.backend, "duration_s": args.duration_s,
           "kinds": summarize(records, bound)}
    text = json.dumps(res, indent=2)
    if args.out is not None:
        args.out.write_text(text + "\n")
        args.out.with_suffix(".records.json").write_text(json.dumps(records) + "\n")  # every attempt
    sys.stdout.write(text + "\n")
    return res


if __name__ == "__main__":
    main()

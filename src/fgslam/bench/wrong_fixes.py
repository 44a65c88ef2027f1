"""Wrong fixes on a real traverse: the reference pass's fixes with a share replaced by wrong ones.

``python -m fgslam.bench.wrong_fixes DIR [--config backend.yaml] [--fraction 0.2] [--seed 0]
[--backend isam2]``: one online pass of BACKEND + reloc on the ``fgslam sim`` directory DIR (its
fixes), then a replay of the same fixes with ``fraction`` of them (seeded choice) moved 5-50 m in
a random direction; prints both ATEs, the rise in %, and how many wrong fixes were accepted (JSON).
The long-traverse defaults apply as in a comparison (:mod:`fgslam.long_traverse`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys

import numpy as np

from reloc.measurements import GlobalFix

log = logging.getLogger(__name__)


def corrupt_fixes(fixes: list[GlobalFix], fraction: float, offsets_m: tuple[float, float] = (5.0, 50.0),
                  seed: int = 0) -> tuple[list[GlobalFix], np.ndarray]:
    """``fixes`` with ``round(fraction * n)`` of them (seeded) moved by a distance drawn uniformly in
    ``offsets_m`` in a uniform direction; returns the list and the (n,) bool mask of wrong ones."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    rng = np.random.default_rng(seed)
    n = len(fixes)
    wrong = np.zeros(n, dtype=bool)
    wrong[rng.choice(n, size=round(fraction * n), replace=False)] = True
    out = []
    for f, w in zip(fixes, wrong):
        if w:
            d, a = rng.uniform(*offsets_m), rng.uniform(-np.pi, np.pi)
            f = dataclasses.replace(f, x_m=f.x_m + d * np.cos(a), y_m=f.y_m + d * np.sin(a))
        out.append(f)
    return out, wrong


def main(argv: list[str] | None = None) -> dict:
    from pathlib import Path

    from fgslam import metrics as M
    from fgslam.backends.registry import make_backend
    from fgslam.compare import relocalizer_set
    from fgslam.config_file import load_compare_config
    from fgslam.fix_sources import OnlineFixes, ReplayedFixes
    from fgslam.inputs import check_stream, load_sim_dir, truth_of
    from fgslam.long_traverse import backend_overrides_for
    from fgslam.runner import run_backend

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--config", type=Path)
    ap.add_argument("--fraction", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="isam2")
    args = ap.parse_args(argv)
    cfg = load_compare_config(args.config)
    inputs = load_sim_dir(args.directory)
    runner = check_stream(inputs, cfg.runner)
    gt = truth_of(inputs)
    over = backend_overrides_for(args.backend, cfg.backend_overrides.get(args.backend), gt.t[-1] - gt.t[0],
                                 cfg.long_traverse)
    good = run_backend(make_backend(args.backend, inputs.initial, over), inputs.measurements,
                       OnlineFixes(relocalizer_set(inputs, cfg)), config=runner)
    fixes = [a.fix for a in good.attempts if a.fix is not None]
    bad_fixes, wrong = corrupt_fixes(fixes, args.fraction, seed=args.seed)
    bad = run_backend(make_backend(args.backend, inputs.initial, over), inputs.measurements,
                      ReplayedFixes(bad_fixes), config=runner)
    wrong_keys = {(f.t_meas, f.x_m, f.y_m) for f, w in zip(bad_fixes, wrong) if w}
    accepted_wrong = sum(1 for o in bad.outcomes if o.accepted and (o.fix.t_meas, o.fix.x_m, o.fix.y_m) in wrong_keys)
    retracted = len(bad.stats.extra.get("retracted_fixes", []))
    ate_good, ate_bad = M.ate(good.final, gt).rmse, M.ate(bad.final, gt).rmse
    out = {"directory": str(args.directory), "backend": args.backend, "overrides": over, "fixes": len(fixes),
           "wrong": int(wrong.sum()), "wrong_accepted_at_first": accepted_wrong, "retracted": retracted,
           "ate_good_m": ate_good, "ate_with_wrong_m": ate_bad, "ate_rise_pct": 100.0 * (ate_bad / ate_good - 1.0)}
    sys.stdout.write(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()

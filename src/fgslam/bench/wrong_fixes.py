"""Wrong fixes on a real traverse: a share of the shared fixes replaced by wrong ones, every back-end.

``fgslam bench wrong-fixes DIR... [--fraction 0.2] [--offsets 5,50] [--backends isam2,ekf]``: per
``fgslam sim`` directory, one online pass of the reference back-end with relocalization gives the
fix list (as ``fgslam compare`` shares it); every back-end then runs with those fixes (the
reference's own online pass; a replay for the others) and with the same list where a seeded
``fraction`` of the fixes is moved by a distance uniform in ``offsets_m`` in a uniform direction,
with the match's own covariance, inliers and RMSE (confidently wrong). The table gives, per
back-end, the ATE and maximum error with good fixes and with wrong ones, the rise, and how many
wrong fixes the back-end accepted (and, for the smoother, retracted later). The settings are
``fgslam run``'s: the directory's ``backend.yaml`` unless ``--config``, the long-traverse defaults
(:mod:`fgslam.long_traverse`). Issue goal: with 20 % wrong fixes of 5-50 m, iSAM2 + reloc's ATE
rises by less than 10 %.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam.errors import InputFileError
from reloc.measurements import GlobalFix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WrongFixBenchConfig:
    """``fraction`` of the fixes made wrong, moved by a distance uniform in ``offsets_m``; the
    ``seed`` of that choice; the back-ends (the first is the reference that makes the fixes);
    ``duration_s``: the first seconds of each stream only (None: all of it)."""

    fraction: float = 0.2
    offsets_m: tuple[float, float] = (5.0, 50.0)
    seed: int = 0
    backends: tuple[str, ...] = ("isam2", "ekf")
    duration_s: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.fraction <= 1.0:
            raise InputFileError(f"--fraction must be in [0, 1], got {self.fraction}")
        lo, hi = self.offsets_m
        if not 0.0 < lo <= hi:
            raise InputFileError(f"--offsets must be 0 < LO <= HI metres, got {lo}, {hi}")
        if not self.backends:
            raise InputFileError("--backends: at least one back-end is needed")
        if self.duration_s is not None and not self.duration_s > 0:
            raise InputFileError(f"--duration-s must be > 0, got {self.duration_s}")


def corrupt_fixes(fixes: list[GlobalFix], fraction: float, offsets_m: tuple[float, float] = (5.0, 50.0),
                  seed: int = 0) -> tuple[list[GlobalFix], np.ndarray]:
    """``fixes`` with ``round(fraction * n)`` of them (seeded) moved by a distance drawn uniformly in
    ``offsets_m`` in a uniform direction (without a height: one read at the right place would tell
    them apart); returns the list and the (n,) bool mask of wrong ones."""
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
            f = dataclasses.replace(f, x_m=f.x_m + d * np.cos(a), y_m=f.y_m + d * np.sin(a), height=None)
        out.append(f)
    return out, wrong


def _fix_id(f: GlobalFix) -> tuple[float, float, float]:
    return (f.t_meas, f.x_m, f.y_m)


def bench_directory(directory: Path, cfg: WrongFixBenchConfig, config: Path | None = None,
                    progress: Callable[[str], None] | None = None) -> dict:
    """The wrong-fix experiment on one ``fgslam sim`` directory (see module doc), as a JSON-ready dict."""
    from fgslam import metrics as M
    from fgslam.fix_sources import OnlineFixes, ReplayedFixes
    from fgslam.run_setup import RunSetup

    say = progress or (lambda s: None)
    setup = RunSetup.of_directory(directory, config, cfg.duration_s)
    gt = setup.gt

    def pass_(name, fixes):
        return setup.run(setup.backend(name), fixes)

    ref = cfg.backends[0]
    say(f"{directory.name}: {ref} + reloc (online: the shared fixes)")
    good = {ref: pass_(ref, OnlineFixes(setup.relocalizers()))}
    attempts = good[ref].attempts
    fixes = [a.fix for a in attempts if a.fix is not None]
    if not fixes:
        raise InputFileError(f"{directory}: the reference pass ({ref} + reloc) made no fix: nothing to corrupt")
    bad_fixes, wrong = corrupt_fixes(fixes, cfg.fraction, cfg.offsets_m, cfg.seed)
    wrong_ids = {_fix_id(f) for f, w in zip(bad_fixes, wrong) if w}
    rows = {}
    for name in cfg.backends:
        if name not in good:
            say(f"{directory.name}: {name} + reloc (the shared fixes replayed)")
            good[name] = pass_(name, ReplayedFixes(fixes))
        say(f"{directory.name}: {name} + reloc with {int(wrong.sum())} wrong fixes")
        bad = pass_(name, ReplayedFixes(bad_fixes))
        ate_good, ate_bad = M.ate(good[name].final, gt), M.ate(bad.final, gt)
        accepted = [o for o in bad.outcomes if o.accepted]
        rows[name] = {
            "ate_good_m": ate_good.rmse, "max_good_m": ate_good.max,
            "ate_with_wrong_m": ate_bad.rmse, "max_with_wrong_m": ate_bad.max,
            "ate_rise_pct": 100.0 * (ate_bad.rmse / ate_good.rmse - 1.0),
            "good_accepted": sum(1 for o in good[name].outcomes if o.accepted),
            "accepted_with_wrong": len(accepted),
            "wrong_accepted": sum(1 for o in accepted if _fix_id(o.fix) in wrong_ids),
            "retracted": len(bad.stats.extra.get("retracted_fixes", [])),
        }
    return {"directory": str(directory), "reference": ref, "duration_s": setup.span_s, "attempts": len(attempts),
            "fixes": len(fixes), "wrong": int(wrong.sum()), "backends": rows}


def summary_rows(results: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Columns and rows of the table: one row per directory and back-end."""
    cols = ["run", "back-end", "fixes (wrong)", "ATE good [m]", "max good [m]", "ATE with wrong [m]",
            "max with wrong [m]", "rise [%]", "wrong accepted", "retracted"]
    rows = []
    for r in results:
        for name, b in r["backends"].items():
            rows.append([Path(r["directory"]).name, f"{name} + reloc", f"{r['fixes']} ({r['wrong']})",
                         f"{b['ate_good_m']:.4f}", f"{b['max_good_m']:.3f}", f"{b['ate_with_wrong_m']:.4f}",
                         f"{b['max_with_wrong_m']:.3f}", f"{b['ate_rise_pct']:+.1f}", str(b["wrong_accepted"]),
                         str(b["retracted"])])
    return cols, rows

"""``python -m fgslam.bench.slip DIR``: the wheel-slip monitor replayed over a ``fgslam sim`` bag,
against the truth.

The monitor (:mod:`reloc.slip`) needs no back-end: it sees the odometry steps and the landmark
frames, so the replay is fast (the bag read dominates). Over every determined check the truth
gives the rover's real slip over the check's interval, ``1 - |p_truth(t) - p_truth(t_ref)| /
wheel``. Reported: the checks (by kind), the undetermined comparisons, the slipping checks and
the slip spells (corrections started); for the slipping checks, the true slip at them (a false
alarm is a slipping check whose true slip is below ``SlipConfig.min_slip``); and the visual
translation's error against the truth in its own sigmas (median / p90 / p99, 0.67 / 1.64 / 2.58
for a Gaussian), which is what ``visual_cov_scale`` was measured from.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np


def replay(directory: Path, config=None) -> dict:
    """The monitor over the bag of ``directory`` with ``config`` (:class:`reloc.slip.SlipConfig`)."""
    from fgslam.inputs import load_sim_dir
    from fgslam.runner import MOTION_INPUTS
    from reloc.kinds import kind_of
    from reloc.measurements import GroundTruthPose
    from reloc.odometry import OdometryAssembler
    from reloc.rows import RowBuffer
    from reloc.slip import SlipMonitor

    inputs = load_sim_dir(directory)
    mon, odo, truth = SlipMonitor(config), OdometryAssembler(), RowBuffer(4)
    for m in inputs.measurements:
        if isinstance(m, MOTION_INPUTS):
            step = odo.push(m)
            if step is not None:
                mon.correct(step)
        elif isinstance(m, GroundTruthPose):
            truth.append((m.t, *m.position_m))
        else:
            mon.observe(kind_of(m).name, m)
    gt = truth.array()
    if not len(gt):
        raise SystemExit(f"{directory}: no ground truth in the bag")
    checks = mon.checks
    t, t_ref = np.array([c.t for c in checks]), np.array([c.t_ref for c in checks])
    p = np.stack([np.interp(t, gt[:, 0], gt[:, i]) for i in (1, 2, 3)], axis=1)
    p_ref = np.stack([np.interp(t_ref, gt[:, 0], gt[:, i]) for i in (1, 2, 3)], axis=1)
    true_m = np.linalg.norm(p - p_ref, axis=1)
    wheel = np.array([c.wheel_m for c in checks])
    visual = np.array([c.visual_m for c in checks])
    sigma_m = np.array([c.slip_sigma * c.wheel_m for c in checks])
    slipping = np.array([c.slipping for c in checks], dtype=bool)
    true_slip = 1.0 - true_m / np.maximum(wheel, 1e-9)
    z = np.abs(visual - true_m) / np.maximum(sigma_m, 1e-12)
    kinds = dict(Counter(c.kind for c in checks))
    cfg = mon.cfg
    return {
        "directory": str(directory), **mon.stats(), "checks_by_kind": kinds,
        "false_alarms": int(np.sum(slipping & (np.abs(true_slip) < cfg.min_slip))),
        "true_slip_at_slipping": np.round(true_slip[slipping], 3).tolist(),
        "visual_error_sigmas_p50_p90_p99": np.round(np.percentile(z, [50, 90, 99]), 2).tolist() if len(z) else [],
        "true_slip_max": float(true_slip.max()) if len(true_slip) else 0.0,
    }


def main(argv: list[str] | None = None) -> dict:
    from fgslam.bench.sim_dir import replay_main

    return replay_main(__doc__.splitlines()[0], replay, argv)


if __name__ == "__main__":
    main()

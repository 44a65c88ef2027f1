"""``python -m fgslam.bench.gyro DIR``: the gyro monitor replayed over a ``fgslam sim`` bag, against
the truth.

The monitor (:mod:`reloc.gyro`) needs no back-end: it sees the odometry steps and the landmark
frames, so the replay is fast (the bag read dominates). Over every determined check the truth
gives the heading the IMU really got wrong over the check's interval: the change of
``yaw(R_imu) - yaw(R_true)`` between the two frames. Reported: the checks (by kind), the
undetermined comparisons, the biased checks and the bias spells (corrections started); the true
bias at the biased checks (a false alarm is a biased check whose true bias is below
``GyroConfig.min_bias_radps``); and the visual heading error's error against the truth in its
own sigmas (median / p90 / p99, 0.67 / 1.64 / 2.58 for a Gaussian), which is what
``cov_scale`` was measured from.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np


def replay(directory: Path, config=None) -> dict:
    """The monitor over the bag of ``directory`` with ``config`` (:class:`reloc.gyro.GyroConfig`)."""
    from scipy.spatial.transform import Rotation

    from fgslam.inputs import load_sim_dir
    from fgslam.runner import MOTION_INPUTS
    from reloc.geometry import wrap_angle, yaw_of
    from reloc.gyro import GyroMonitor
    from reloc.kinds import kind_of
    from reloc.measurements import GroundTruthPose
    from reloc.odometry import OdometryAssembler
    from reloc.rows import RowBuffer

    inputs = load_sim_dir(directory)
    mon, odo = GyroMonitor(config), OdometryAssembler()
    truth, imu = RowBuffer(2), RowBuffer(2)  # (t, yaw)
    for m in inputs.measurements:
        if isinstance(m, MOTION_INPUTS):
            step = odo.push(m)
            if step is not None:
                imu.append((step.t1, yaw_of(step.R_ref_base1)))
                mon.correct(step)
        elif isinstance(m, GroundTruthPose):
            truth.append((m.t, yaw_of(Rotation.from_quat(m.quat_xyzw).as_matrix())))
        else:
            mon.observe(kind_of(m).name, m)
    gt, im = truth.array(), imu.array()
    if not len(gt):
        raise SystemExit(f"{directory}: no ground truth in the bag")
    checks = mon.checks

    def imu_error(t: np.ndarray) -> np.ndarray:  # yaw(R_imu) - yaw(R_true), unwrapped in time
        e = np.unwrap(wrap_angle(np.interp(gt[:, 0], im[:, 0], np.unwrap(im[:, 1])) - np.unwrap(gt[:, 1])))
        return np.interp(t, gt[:, 0], e)

    t, t_ref = np.array([c.t for c in checks]), np.array([c.t_ref for c in checks])
    true_delta = -(imu_error(t) - imu_error(t_ref)) if len(checks) else np.zeros(0)
    T = t - t_ref
    true_bias = -true_delta / np.maximum(T, 1e-9)
    delta = np.array([c.delta_rad for c in checks])
    sigma = np.array([c.delta_sigma_rad for c in checks])
    biased = np.array([c.biased for c in checks], dtype=bool)
    z = np.abs(delta - true_delta) / np.maximum(sigma, 1e-12)
    cfg = mon.cfg
    return {
        "directory": str(directory), **mon.stats(), "checks_by_kind": dict(Counter(c.kind for c in checks)),
        "false_alarms": int(np.sum(biased & (np.abs(true_bias) < cfg.min_bias_radps))),
        "missed": int(np.sum(~biased & (np.abs(true_bias) > 2 * cfg.min_bias_radps))),
        "true_bias_at_biased": np.round(true_bias[biased], 6).tolist(),
        "estimated_bias_at_biased": np.round([c.bias_radps for c in checks if c.biased], 6).tolist(),
        "heading_error_sigmas_p50_p90_p99": np.round(np.percentile(z, [50, 90, 99]), 2).tolist() if len(z) else [],
        "sigma_rad_median": float(np.median(sigma)) if len(sigma) else None,
        "true_bias_max": float(np.max(np.abs(true_bias))) if len(true_bias) else 0.0,
    }


def main(argv: list[str] | None = None) -> dict:
    from fgslam.bench.sim_dir import replay_main

    return replay_main(__doc__.splitlines()[0], replay, argv)


if __name__ == "__main__":
    main()

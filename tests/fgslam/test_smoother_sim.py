"""The smoother on a seeded simulator run (rendered stereo detections with false positives, slip,
IMU drift): accuracy, consistency, late fixes through the real measurement stream."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.smoother import Isam2Smoother
from fgslam.smoother.synthetic import SyntheticRun, ate_m, drive, synthetic_fixes


@pytest.fixture(scope="module")
def sim_run():
    sim = pytest.importorskip("sim.simulate")
    from sim.config import SimConfig, TraverseConfig

    run = sim.simulate(SimConfig(world="my2022", seed=3, traverse=TraverseConfig(distance_m=30.0)))
    return SyntheticRun(run.measurements, np.asarray(run.ground_truth.t), np.asarray(run.ground_truth.T_world_base),
                        np.zeros((0, 3)), run.initial_pose)


def _dead_reckoning_ate(run: SyntheticRun) -> float:
    """ATE of the smoother's own odometry with no rocks and no fixes (the drift to beat)."""
    sm = Isam2Smoother(run.initial_pose)
    out = drive(sm, [m for m in run.measurements if type(m).__name__ != "RockObservations"], [])
    return ate_m(run, out.est_t, out.est_T)


@pytest.mark.slow
def test_smoother_on_simulated_run_beats_dead_reckoning_and_uses_late_fixes(sim_run):
    dr = _dead_reckoning_ate(sim_run)
    sm = Isam2Smoother(sim_run.initial_pose)
    drive(sm, sim_run.measurements, [])
    tr = sm.trajectory()
    ate_slam = ate_m(sim_run, tr.t, tr.T_world_base)
    assert len(sm.landmark_map("rocks")) > 20
    assert ate_slam < dr, (ate_slam, dr)
    # 3-sigma envelope of the smoothed xy positions
    err = tr.positions_m[:, :2] - np.array([sim_run.gt_at(t)[:2, 3] for t in tr.t])
    sig = np.sqrt(np.stack([tr.cov[:, 0, 0], tr.cov[:, 1, 1]], axis=1))
    assert np.mean(np.all(np.abs(err) <= 3 * sig, axis=1)) > 0.85
    # late fixes (1-30 s) from ground truth + noise: accepted and not harmful
    fixes = [f for f, _ in synthetic_fixes(sim_run, np.random.default_rng(0), period_s=8.0, delay_s=(1.0, 20.0),
                                           sigma_xy_m=0.3)]
    smf = Isam2Smoother(sim_run.initial_pose)
    outf = drive(smf, sim_run.measurements, fixes)
    assert sum(o.accepted for o in outf.outcomes) >= 0.8 * len(fixes)
    trf = smf.trajectory()
    assert ate_m(sim_run, trf.t, trf.T_world_base) < max(ate_slam, 0.3)

"""Sensor statistics on a seeded short run: command drift, IMU, stereo precision/recall and noise."""

from __future__ import annotations

import numpy as np
import pytest
from _sim_runs import dense_run, short_run
from scipy.spatial.transform import Rotation

from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    RockObservations,
    WheelOdometry,
    sort_key,
)
from reloc.odometry import OdometryAssembler


def _of(run, kind):
    return [m for m in run.measurements if isinstance(m, kind)]


def _gt_at(run, t):
    k = np.searchsorted(run.ground_truth.t, t)
    assert run.ground_truth.t[k] == pytest.approx(t)
    return run.ground_truth.T_world_base[k]


def test_streams_rates_order_and_start_pose():
    run = short_run()
    assert [sort_key(m) for m in run.measurements] == sorted(sort_key(m) for m in run.measurements)
    cmd, imu, gt = _of(run, CmdVel), _of(run, ImuSample), _of(run, GroundTruthPose)
    rocks, wheel = _of(run, RockObservations), _of(run, WheelOdometry)
    assert len(cmd) == len(imu) == len(gt) == len(wheel) == len(run.ground_truth)
    np.testing.assert_allclose(np.diff([m.t for m in imu]), 1 / 30, atol=1e-9)
    np.testing.assert_allclose(np.diff([m.t for m in rocks]), 0.5, atol=1e-9)
    assert sum(len(r) == 0 for r in rocks) < len(rocks)
    assert run.initial_pose.t == imu[0].t
    np.testing.assert_allclose(run.initial_pose.T_world_base, run.ground_truth.T_world_base[0])
    assert np.all(np.diag(run.initial_pose.cov) <= 1e-4)
    assert run.stats["distance_m"] == pytest.approx(30.0, rel=0.03)


@pytest.mark.parametrize("make_run", [short_run, dense_run], ids=["my2022", "my2020"])
def test_command_dead_reckoning_drift_is_in_the_band(make_run):
    """Integrate /cmd_vel speed along the IMU orientation the way the back-ends do."""
    run = make_run()
    odo = OdometryAssembler("cmd")
    p = run.ground_truth.positions_m[0].copy()
    for m in run.measurements:
        if isinstance(m, (CmdVel, ImuSample)):
            step = odo.push(m)
            if step is not None:
                p += step.R_ref_base0 @ np.array([step.v_mps * step.dt, 0.0, 0.0])
    truth = run.ground_truth.positions_m
    distance = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    drift_pct = 100 * np.linalg.norm(p[:2] - truth[-1, :2]) / distance
    assert 1.5 <= drift_pct <= 2.5
    assert drift_pct == pytest.approx(run.stats["drift_pct"], abs=0.2)
    # the command over-states the true speed (wheel slip), by a few percent
    v_cmd = np.array([m.v_mps for m in _of(run, CmdVel)])
    v_true = np.linalg.norm(np.diff(truth, axis=0), axis=1) * 30
    assert 1.0 < v_cmd.sum() / v_true.sum() < 1.15


def test_imu_orientation_gravity_referenced_with_drifting_yaw():
    run = short_run()
    imu = _of(run, ImuSample)
    R_imu = Rotation.from_quat([m.quat_xyzw for m in imu])
    R_true = Rotation.from_matrix(run.ground_truth.T_world_base[:, :3, :3])
    err = (R_imu * R_true.inv()).as_rotvec()  # world-frame error
    assert np.abs(err[:, :2]).max() < np.deg2rad(0.5)  # roll/pitch held by gravity
    assert 0.0 < np.abs(err[-1, 2]) < np.deg2rad(2.0)  # yaw drifts, slowly
    assert np.abs(err[0]).max() < np.deg2rad(0.5)
    gyro = np.array([m.gyro_radps for m in imu])
    dR = (R_true[:-1].inv() * R_true[1:]).as_rotvec() * 30
    assert np.abs(np.mean(gyro[:-1] - dR, axis=0)).max() < 1e-3
    acc = np.array([m.accel_mps2 for m in imu])
    assert np.median(np.linalg.norm(acc, axis=1)) == pytest.approx(9.81, abs=0.05)
    gravity_body = R_true.inv().apply([0.0, 0.0, 9.81])
    assert np.median(np.linalg.norm(acc - gravity_body, axis=1)) < 0.2


@pytest.mark.parametrize("make_run", [short_run, dense_run], ids=["my2022", "my2020"])
def test_stereo_precision_and_recall_match_the_published_detector(make_run):
    run = make_run()
    st = run.config.sensors.stereo
    n_true = sum(int(np.sum(r >= 0)) for r in run.stereo_rock)
    n_det = sum(len(r) for r in run.stereo_rock)
    n_vis = sum(len(v) for v in run.stereo_visible)
    assert n_vis > 1000
    assert n_true / n_det == pytest.approx(st.precision, abs=0.05)
    assert n_true / n_vis == pytest.approx(st.recall, abs=0.05)
    assert run.stats["stereo_precision"] == pytest.approx(n_true / n_det)
    # only visible rocks are detected, each at most once per frame
    for rock, vis in zip(run.stereo_rock, run.stereo_visible):
        true = rock[rock >= 0]
        assert np.all(np.isin(true, vis)) and len(np.unique(true)) == len(true)


@pytest.mark.parametrize("make_run", [short_run, dense_run], ids=["my2022", "my2020"])
def test_stereo_positions_and_covariance_are_consistent_in_base_link(make_run):
    run = make_run()
    frames = _of(run, RockObservations)
    nees, ranges, size_ratio = [], [], []
    for obs, rock in zip(frames, run.stereo_rock):
        T = _gt_at(run, obs.t)
        true = rock >= 0
        if not np.any(true):
            continue
        xyz_true_b = (run.rocks_true.xyz_m[rock[true]] - T[:3, 3]) @ T[:3, :3]
        r = obs.xyz_base_m[true] - xyz_true_b
        nees.extend(np.einsum("ni,nij,nj->n", r, np.linalg.inv(obs.cov_base_m2[true]), r))
        ranges.extend(np.linalg.norm(xyz_true_b, axis=1))
        size_ratio.extend(obs.size_m[true] / run.rocks_true.size_m[rock[true]])
    nees = np.array(nees)
    assert len(nees) > 500
    assert np.mean(nees) == pytest.approx(3.0, abs=0.3)  # chi-square with 3 dof
    assert max(ranges) < run.config.sensors.stereo.max_range_m + 0.2
    assert np.median(size_ratio) == pytest.approx(1.0, abs=0.05)
    # depth noise grows with range: far covariances are larger
    big = [np.trace(c) for o in frames for c, x in zip(o.cov_base_m2, o.xyz_base_m) if np.linalg.norm(x) > 7]
    small = [np.trace(c) for o in frames for c, x in zip(o.cov_base_m2, o.xyz_base_m) if np.linalg.norm(x) < 3]
    assert np.median(big) > 10 * np.median(small)


def test_orbital_catalog_of_the_run():
    run = short_run()
    true = run.catalog_rock >= 0
    assert len(run.catalog) == run.stats["n_catalog"]
    assert true.sum() / len(run.catalog) == pytest.approx(0.44, abs=0.08)  # 294 rocks: small-sample
    err = run.catalog.xy_m[true] - run.rocks_true.xyz_m[run.catalog_rock[true], :2]
    assert np.sqrt(np.mean(err**2)) < 0.3


def test_runs_are_seeded():
    from sim.config import SimConfig, TraverseConfig, WorldGenConfig
    from sim.simulate import simulate

    def run(seed):
        return simulate(SimConfig(world="cnes", seed=seed, worldgen=WorldGenConfig(resolution_m=0.4, n_rocks=100),
                                  traverse=TraverseConfig(distance_m=3.0)))

    a, b, c = run(7), run(7), run(8)
    assert a.stats == b.stats
    ra, rb = _of(a, RockObservations), _of(b, RockObservations)
    assert all(np.array_equal(x.xyz_base_m, y.xyz_base_m) for x, y in zip(ra, rb))
    np.testing.assert_array_equal(a.ground_truth.T_world_base, b.ground_truth.T_world_base)
    assert a.stats["distance_m"] != c.stats["distance_m"] or not np.array_equal(a.catalog.xy_m, c.catalog.xy_m)

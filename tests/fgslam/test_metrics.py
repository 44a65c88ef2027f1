"""Metrics against hand-computed cases, and ATE against evo's APE on our TUM files."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fgslam import metrics as M
from reloc.backend import Trajectory


def _traj(t, xy, yaw, z=None, cov=None) -> Trajectory:
    n = len(t)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", np.asarray(yaw, float).reshape(-1, 1)).as_matrix()
    T[:, 0, 3], T[:, 1, 3] = xy[:, 0], xy[:, 1]
    if z is not None:
        T[:, 2, 3] = z
    return Trajectory(np.asarray(t, float), T, cov)


def _line(n=11, speed=1.0):
    t = np.arange(n, dtype=float)
    return t, np.column_stack([speed * t, np.zeros(n)]), np.zeros(n)


def test_ate_constant_offset_is_its_norm():
    t, xy, yaw = _line()
    gt = _traj(t, xy, yaw)
    est = _traj(t, xy + [3.0, 4.0], yaw)
    s = M.ate(est, gt)
    assert s.rmse == pytest.approx(5.0) and s.mean == pytest.approx(5.0) and s.max == pytest.approx(5.0)
    assert s.n == 11
    # an offset is a rigid motion: the SE(2)-aligned ATE removes it
    assert M.ate(est, gt, align_se2=True).rmse == pytest.approx(0.0, abs=1e-9)


def test_ate_hand_computed_growing_error():
    t = np.array([0.0, 1.0, 2.0])
    gt = _traj(t, np.array([[0, 0], [1, 0], [2, 0]], float), np.zeros(3))
    est = _traj(t, np.array([[0, 0], [1, 1], [2, 2]], float), np.zeros(3))
    s = M.ate(est, gt)
    assert s.rmse == pytest.approx(np.sqrt(5 / 3))
    assert s.mean == pytest.approx(1.0)
    assert s.max == pytest.approx(2.0)
    assert s.median == pytest.approx(1.0)


def test_ate_parts_split_plane_and_height():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    xy = np.column_stack([t, np.zeros(4)])
    gt = _traj(t, xy, np.zeros(4), z=np.full(4, 10.0))
    est = _traj(t, xy + [0.3, 0.4], np.zeros(4), z=10.0 + np.array([0.0, -1.2, 1.2, 0.0]))
    planar, height = M.ate_parts(est, gt)
    assert planar.rmse == pytest.approx(0.5) and planar.max == pytest.approx(0.5)
    assert height.rmse == pytest.approx(np.sqrt(2 * 1.44 / 4)) and height.max == pytest.approx(1.2)
    # the 3D ATE's squares are the sum of its parts'
    assert M.ate(est, gt).rmse ** 2 == pytest.approx(planar.rmse ** 2 + height.rmse ** 2)


def test_ate_interpolates_truth_at_estimate_stamps():
    gt = _traj(np.array([0.0, 2.0]), np.array([[0.0, 0.0], [2.0, 0.0]]), np.zeros(2))
    est = _traj(np.array([1.0]), np.array([[1.0, 0.5]]), np.zeros(1))
    est2 = Trajectory(np.array([1.0, 1.5]), np.concatenate([est.T_world_base, est.T_world_base]))
    s = M.ate(est2, gt)  # errors: |(1,.5)-(1,0)| = .5 and |(1,.5)-(1.5,0)| = sqrt(.5)
    assert s.rmse == pytest.approx(np.sqrt((0.25 + 0.5) / 2))


def test_umeyama_recovers_rotation_and_translation(rng):
    src = rng.normal(size=(20, 2))
    a = 0.7
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = src @ R.T + [2.0, -1.0]
    R_fit, t_fit = M.umeyama_se2(src, dst)
    assert np.allclose(R_fit, R) and np.allclose(t_fit, [2.0, -1.0])


def test_aligned_ate_removes_rigid_transform_only():
    t, xy, yaw = _line(21)
    xy[:, 1] = 0.1 * t**1.5  # a curved path
    gt = _traj(t, xy, yaw)
    a = 0.3
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    est = _traj(t, xy @ R.T + [1.0, 2.0], yaw + a)
    assert M.ate(est, gt).rmse > 1.0
    assert M.ate(est, gt, align_se2=True).rmse == pytest.approx(0.0, abs=1e-9)


def test_rpe_zero_for_rigidly_moved_path_and_hand_value_for_scale_error():
    t, xy, yaw = _line(31)  # 30 m straight line at 1 m/s
    gt = _traj(t, xy, yaw)
    est = _traj(t, xy + [5.0, -2.0], yaw)
    assert M.rpe(est, gt, 10.0).max == pytest.approx(0.0, abs=1e-9)
    # 10 % too long: pairs every 10 m of the estimate's own path, i.e. every 10 / 1.1 s
    est_scaled = _traj(t, 1.1 * xy, yaw)
    s = M.rpe(est_scaled, gt, 10.0)
    assert s.n == 3  # ends at 10, 19, 28 s (11, 9.9 -> reset, ...): 10 s apart each after the first
    assert s.max == pytest.approx(1.0)
    f = M.rpe(est_scaled, gt, 5, "frames")  # pairs (0, 5), (5, 10), ... : 0.5 m error each
    assert f.n == 6 and f.rmse == pytest.approx(0.5)
    with pytest.raises(M.MetricsError, match="unit"):
        M.rpe(est, gt, 10.0, "seconds")


def test_associate_stamps_nearest_within_reach():
    ta = np.array([0.0, 1.0, 2.004, 3.02, 4.0])
    tb = np.array([0.005, 0.995, 2.0, 3.0, 3.995, 4.006])
    ia, ib = M.associate_stamps(ta, tb, 0.01)
    assert ia.tolist() == [0, 1, 2, 4] and ib.tolist() == [0, 1, 2, 4]  # 3.02 has no partner


def _wobbly(t, rng):
    """A 3D path with roll, pitch and yaw changing (so RPE sees full SE(3) rotations)."""
    yaw = 0.3 * np.sin(t / 10)
    xy = np.column_stack([np.cumsum(np.cos(yaw)) * 0.02, np.cumsum(np.sin(yaw)) * 0.02])
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = Rotation.from_euler("zyx", np.column_stack([yaw, 0.05 * np.sin(t / 3), 0.04 * np.cos(t / 5)])).as_matrix()
    T[:, :2, 3], T[:, 2, 3] = xy, 0.2 * np.sin(t / 7)
    return T


def test_rpe_matches_evo_rpe_on_tum_files(tmp_path, rng):
    """fgslam's RPE equals evo_rpe's (`--delta 10 --delta_unit m`, and frames) on files it wrote."""
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.main_rpe import rpe as evo_rpe
    from evo.tools import file_interface

    from fgslam.io.tum import write_tum

    t = np.arange(0, 120, 1 / 30)
    T_gt = _wobbly(t, rng)
    gt = Trajectory(t, T_gt, None)
    idx = np.arange(0, len(t), 3)
    T_est = T_gt[idx].copy()
    T_est[:, :2, 3] += np.column_stack([0.004 * t[idx], -0.002 * t[idx]]) + rng.normal(0, 0.01, (len(idx), 2))
    T_est[:, :3, :3] = T_est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.003, (len(idx), 3))).as_matrix()
    est = Trajectory(t[idx] + 0.002, T_est, None)  # stamps 2 ms off the truth's: associated, not interpolated
    write_tum(tmp_path / "gt.tum", gt.t, gt.T_world_base)
    write_tum(tmp_path / "est.tum", est.t, est.T_world_base)
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    ests = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    ref, ests = sync.associate_trajectories(ref, ests, max_diff=0.01)
    for delta, unit, evo_unit in ((10.0, "m", evo_metrics.Unit.meters), (30, "frames", evo_metrics.Unit.frames)):
        res = evo_rpe(copy.deepcopy(ref), copy.deepcopy(ests), evo_metrics.PoseRelation.translation_part,
                      delta=delta, delta_unit=evo_unit)  # evo reduces its inputs in place
        ours = M.rpe(est, gt, delta, unit)
        assert ours.n == len(res.np_arrays["error_array"]) > 5
        for stat, key in (("rmse", "rmse"), ("mean", "mean"), ("median", "median"), ("max", "max")):
            assert getattr(ours, stat) == pytest.approx(res.stats[key], rel=1e-6), (unit, stat)


def test_consistency_nees_and_inside_fraction():
    t = np.arange(4, dtype=float)
    gt = _traj(t, np.zeros((4, 2)), np.zeros(4))
    cov = np.tile(np.eye(6) * 0.01, (4, 1, 1))  # sigma 0.1 m, 0.1 rad
    # errors of 0, 1, 2, 4 sigma along x
    est = _traj(t, np.array([[0.0, 0], [0.1, 0], [0.2, 0], [0.4, 0]]), np.zeros(4), cov=cov)
    s, series = M.consistency(est, gt)
    assert s.nees_xy_mean == pytest.approx((0 + 1 + 4 + 16) / 4)
    assert s.nees_mean == pytest.approx((0 + 1 + 4 + 16) / 4)
    assert s.inside_3sigma == pytest.approx(0.75)  # 16 > 11.83
    assert s.inside_3sigma_axes == pytest.approx(0.75)
    assert np.allclose(series["sigma_xy"], 0.1)
    assert s.position.dof == 2 and s.yaw.dof == 1 and s.pose.dof == 3
    assert s.position.mean == pytest.approx(s.nees_xy_mean) and s.yaw.mean == pytest.approx(0.0)
    assert s.height.dof == 1 and s.height.mean == pytest.approx(0.0)  # the height exact


def test_the_height_is_tested_against_its_own_sigma(rng):
    """The z error over its own sigma, two-sided: an estimate whose height errors are drawn from
    the sigma it claims is consistent, one claiming a third of it optimistic, three times it
    pessimistic; the planar tests do not see the height."""
    n = 2000
    t = np.arange(n, dtype=float)
    gt = _traj(t, np.zeros((n, 2)), np.zeros(n))
    cov = np.tile(np.eye(6) * 0.01, (n, 1, 1))
    cov[:, 2, 2] = 0.2**2
    est = _traj(t, np.zeros((n, 2)), np.zeros(n), z=rng.normal(0.0, 0.2, n), cov=cov)
    verdicts = {}
    for claim in (1.0, 3.0, 1.0 / 3.0):
        c = cov.copy()
        c[:, 2, 2] = (0.2 / claim) ** 2
        s, series = M.consistency(Trajectory(est.t, est.T_world_base, c), gt)
        verdicts[claim] = s.height.verdict.value
        assert s.position.mean == pytest.approx(0.0) and s.yaw.mean == pytest.approx(0.0)
        assert np.allclose(series["sigma_z"], 0.2 / claim)
    assert verdicts == {1.0: "consistent", 3.0: "optimistic", 1.0 / 3.0: "pessimistic"}
    assert s.to_dict()["height"]["dof"] == 1


def test_consistency_counts_yaw_error_with_wrap():
    t = np.arange(2, dtype=float)
    gt = _traj(t, np.zeros((2, 2)), np.array([np.pi - 0.05, np.pi - 0.05]))
    cov = np.tile(np.eye(6) * 0.01, (2, 1, 1))
    est = _traj(t, np.zeros((2, 2)), np.array([-np.pi + 0.05, -np.pi + 0.05]), cov=cov)
    s, series = M.consistency(est, gt)
    assert np.allclose(series["err_yaw"], 0.1)
    assert s.nees_mean == pytest.approx(1.0)


def test_fix_stats_hand_case():
    t, xy, yaw = _line(11)
    gt = _traj(t, xy, yaw)
    fixes = np.array([[1.0, 0.3, 0.0], [2.0, 0.0, 0.1], [3.0, 1.5, 0.0], [4.5, 0.0, 0.0]])
    s = M.fix_stats(8, fixes, np.array([1.0, 2.0, 3.0, 4.0]), np.array([3.0, 4.0, 5.0, 6.0]),
                    np.array([True, True, False, True]), gt, duration_s=10.0)
    assert s.attempts == 8 and s.fixes == 4 and s.accepted == 3
    assert s.rate_hz == pytest.approx(0.4) and s.accepted_rate_hz == pytest.approx(0.3)
    assert s.position_error_m.median == pytest.approx(0.4)  # errors 0.3, 0, 1.5, 0.5
    assert s.within_m == {"0.5": 0.75, "1": 0.75, "2": 1.0}
    assert s.yaw_error_rad.max == pytest.approx(0.1)
    assert s.latency_s_mean == pytest.approx(2.0)


def test_fix_nees_alone_is_two_sided_and_ignores_the_correlation_factor(rng):
    """Fixes drawn from their own covariance test consistent against it, whatever factor the
    producer sent them with; fixes claiming 10x their error are pessimistic, 0.3x optimistic."""
    t, xy, yaw = _line(401, speed=0.1)
    gt = _traj(t, xy, yaw)
    k = 300
    tm = np.sort(rng.uniform(0, 400, k))
    C = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.0004]])
    e = rng.multivariate_normal(np.zeros(3), C, size=k)
    fixes = np.column_stack([0.1 * tm + e[:, 0], e[:, 1], e[:, 2]])
    sent = np.tile(40.0 * C, (k, 1, 1))  # a correlation factor of 40
    args = (k, fixes, tm, tm + 2.0, np.ones(k, bool), gt, 400.0)
    s = M.fix_stats(*args, cov_xyyaw=sent, cov_alone_xyyaw=np.tile(C, (k, 1, 1)))
    assert s.nees_alone.dof == 3 and s.nees_alone.n == k and s.nees_alone.consistent
    assert s.nees_alone.interval[0] < 3.0 < s.nees_alone.interval[1]
    assert s.nees_mean == pytest.approx(s.nees_alone.mean / 40.0, rel=1e-9)
    assert M.fix_stats(*args, cov_alone_xyyaw=np.tile(10.0 * C, (k, 1, 1))).nees_alone.verdict.value == "pessimistic"
    assert M.fix_stats(*args, cov_alone_xyyaw=np.tile(0.3 * C, (k, 1, 1))).nees_alone.verdict.value == "optimistic"
    d = s.to_dict()
    assert d["nees_alone"]["verdict"] == "consistent" and d["nees_alone"]["dof"] == 3
    assert M.fix_stats(*args).nees_alone is None and M.fix_stats(*args).to_dict()["nees_alone"] is None


def test_error_along_distance_drift_and_bins():
    t, xy, yaw = _line(31)  # 30 m at 1 m/s
    gt = _traj(t, xy, yaw)
    est = _traj(t, xy + np.column_stack([0.01 * t, np.zeros(31)]), yaw)  # 1 cm of error per metre
    dist, err = M.error_along(est, gt)
    assert np.allclose(dist, t) and np.allclose(err, 0.01 * t)
    assert M.drift_pct(est, gt) == pytest.approx(1.0)
    bins = M.error_by_distance(est, gt, 10.0)
    assert [b["to_m"] for b in bins] == [10.0, 20.0, 30.0]
    assert bins[0]["max_m"] == pytest.approx(0.10) and bins[-1]["max_m"] == pytest.approx(0.30)  # (0, 10], ...
    assert bins[1]["rmse_m"] == pytest.approx(np.sqrt(np.mean((0.01 * np.arange(11, 21)) ** 2)))
    with pytest.raises(M.MetricsError, match="step_m"):
        M.error_by_distance(est, gt, 0.0)


def test_runtime_helpers():
    assert M.real_time_factor(100.0, 2.0) == pytest.approx(50.0)
    assert M.improvement_pct(2.0, 0.5) == pytest.approx(75.0)
    assert M.path_length_m(np.array([[0, 0], [3, 4], [3, 5]])) == pytest.approx(6.0)


def test_errors_are_clear():
    gt = _traj(np.array([0.0, 1.0]), np.zeros((2, 2)), np.zeros(2))
    est = _traj(np.array([5.0, 6.0]), np.zeros((2, 2)), np.zeros(2))
    with pytest.raises(M.MetricsError, match="do not overlap"):
        M.ate(est, gt)
    with pytest.raises(M.MetricsError, match="covariance"):
        M.consistency(gt, gt)


def test_ate_matches_evo_ape_on_tum_files(tmp_path, rng):
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    from fgslam.io.tum import write_tum

    t = np.arange(0, 60, 1 / 30)
    yaw = 0.3 * np.sin(t / 10)
    xy = np.column_stack([np.cumsum(np.cos(yaw)) * 0.01, np.cumsum(np.sin(yaw)) * 0.01])
    gt = _traj(t, xy, yaw, z=0.2 * np.sin(t / 7))
    te = t[::3]  # the estimate at 10 Hz, on the truth's stamps
    drift = np.column_stack([0.01 * te, -0.005 * te]) + rng.normal(0, 0.02, (len(te), 2))
    est = _traj(te, xy[::3] + drift, yaw[::3] + 0.01, z=0.2 * np.sin(te / 7) + 0.05)
    write_tum(tmp_path / "gt.tum", gt.t, gt.T_world_base)
    write_tum(tmp_path / "est.tum", est.t, est.T_world_base)
    traj_ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    traj_est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    ours = M.ate(est, gt)
    assert ours.n == traj_est.num_poses
    assert ours.rmse == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)
    assert ours.mean == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.mean), rel=1e-6)
    assert ours.max == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.max), rel=1e-6)

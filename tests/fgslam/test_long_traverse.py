"""The long-traverse defaults (fgslam.long_traverse) and the frame-latency histogram."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.compare import CompareConfig
from fgslam.long_traverse import (
    LongTraverseConfig,
    LongTraverseError,
    backend_overrides_for,
    check_window,
    stream_span_s,
)
from fgslam.timing import LatencyHistogram
from reloc.measurements import CmdVel


def test_a_long_traverse_gets_the_fixed_lag_smoother_unless_told_otherwise():
    cfg = LongTraverseConfig(min_duration_s=1800.0, isam2_fixed_lag_s=90.0, isam2_keyframe_interval_s=2.0)
    assert backend_overrides_for("isam2", None, 1000.0, cfg) is None  # a yard: full history
    long_isam2 = {"fixed_lag_s": 90.0, "calibration_mode": "estimate", "fixes": {"correlation_model": "bias"},
                  "odometry": {"slip_sigma": 0.05}, "keyframes": {"interval_s": 2.0},
                  "landmarks": {"min_frame_interval_s": 1.9, "association": {"persistence_s": 5.0}}}
    assert backend_overrides_for("isam2", None, 3600.0, cfg) == long_isam2
    over = {"calibration": {"yaw_sigma_deg": 0.15}}
    assert backend_overrides_for("isam2", over, 3600.0, cfg) == {**over, **long_isam2}
    assert over == {"calibration": {"yaw_sigma_deg": 0.15}}  # the caller's mapping is not changed
    explicit = {"fixed_lag_s": 0.0, "calibration_mode": "consider", "fixes": {"correlation_model": "producer"},
                "odometry": {"slip_sigma": 0.0}, "keyframes": {"interval_s": 1.0},
                "landmarks": {"min_frame_interval_s": 0.95, "association": {"persistence_s": 2.5}}}
    assert backend_overrides_for("isam2", explicit, 3600.0, cfg) is explicit
    # setting by setting: a section set for another reason still gets the rule's other settings
    scaled = {"landmarks": {"association_cov_scale": 1.5}, "keyframes": {"interval_s": 3.0}}
    # ... and the frame and persistence intervals follow the keyframe interval it sets
    assert backend_overrides_for("isam2", scaled, 3600.0, cfg) == {
        "fixed_lag_s": 90.0, "calibration_mode": "estimate", "fixes": {"correlation_model": "bias"},
        "odometry": {"slip_sigma": 0.05}, "keyframes": {"interval_s": 3.0},
        "landmarks": {"association_cov_scale": 1.5, "min_frame_interval_s": pytest.approx(2.85),
                      "association": {"persistence_s": 7.5}}}
    consider = LongTraverseConfig(isam2_calibration_mode="consider")
    assert backend_overrides_for("isam2", None, 3600.0, consider)["calibration_mode"] == "consider"
    producer = LongTraverseConfig(isam2_fix_correlation_model="producer")
    assert backend_overrides_for("isam2", None, 3600.0, producer)["fixes"] == {"correlation_model": "producer"}
    no_slip = LongTraverseConfig(isam2_slip_sigma=0.0)
    assert backend_overrides_for("isam2", None, 3600.0, no_slip)["odometry"] == {"slip_sigma": 0.0}
    # an odometry section set for another reason (a preset's rotation noise) keeps the rule's slip
    assert backend_overrides_for("isam2", {"odometry": {"sigma_rot_radpsqrts": 9.5e-5}}, 3600.0, cfg)["odometry"] == {
        "sigma_rot_radpsqrts": 9.5e-5, "slip_sigma": 0.05}
    # a fixes section set for another reason keeps the rule's model; an explicit model wins
    assert backend_overrides_for("isam2", {"fixes": {"gate_chi2": 20.0}}, 3600.0, cfg)["fixes"] == {
        "gate_chi2": 20.0, "correlation_model": "bias"}
    assert backend_overrides_for("ekf", over, 3600.0, cfg) == {**over, "forget_distance_m": 40.0,
                                                                 "trajectory_period_s": 1.0, "keep_seen_s": 2.0}
    assert backend_overrides_for("ekf", {"trajectory_period_s": 0.0}, 3600.0, cfg) == {
        "trajectory_period_s": 0.0, "forget_distance_m": 40.0, "keep_seen_s": 2.0}
    assert backend_overrides_for("ekf", over, 1000.0, cfg) is over
    assert backend_overrides_for("dr", None, 3600.0, cfg) is None
    assert backend_overrides_for("isam2", None, float("nan"), cfg) is None  # unknown span


def test_the_long_traverse_keyframe_settings_reach_the_smoother():
    from fgslam.backends.registry import backend_config

    two = LongTraverseConfig(isam2_keyframe_interval_s=2.0)
    smoother = backend_config("isam2", backend_overrides_for("isam2", {"landmarks": {"association_cov_scale": 1.5}},
                                                              3600.0, two))
    assert smoother.keyframes.interval_s == 2.0
    assert smoother.landmarks.min_frame_interval_s == pytest.approx(1.9)
    assert smoother.landmarks.association.persistence_s == pytest.approx(5.0)
    assert smoother.landmarks.association.persistence_n_uncertain == 2  # the smoother's own, kept
    assert smoother.landmarks.association_cov_scale == 1.5
    assert smoother.fixes.correlation_model == "bias"  # the fixes' shared error as variables
    assert smoother.odometry.slip_sigma == 0.05  # the wheels' slip as a variable
    for span in (600.0, 3600.0):  # a yard, and a long traverse at the default: the smoother's own
        default = backend_config("isam2", backend_overrides_for("isam2", None, span, LongTraverseConfig()))
        assert (default.keyframes.interval_s, default.landmarks.min_frame_interval_s) == (1.0, pytest.approx(0.95))
        assert default.landmarks.association.persistence_s == 2.5
    assert backend_config("isam2", None).odometry.slip_sigma == 0.0  # a yard: no slip variable


def test_a_window_shorter_than_the_fix_latency_is_refused():
    check_window(LongTraverseConfig(isam2_fixed_lag_s=10.0), 2.0, 2.0)
    with pytest.raises(LongTraverseError, match="worst fix latency"):
        check_window(LongTraverseConfig(isam2_fixed_lag_s=3.0), 2.0, 2.0)
    with pytest.raises(LongTraverseError, match="isam2_fixed_lag_s"):
        CompareConfig(long_traverse=LongTraverseConfig(isam2_fixed_lag_s=3.0))


def test_stream_span():
    ms = [CmdVel(t, 0.1, 0.0) for t in (5.0, 6.0, 17.5)]
    assert stream_span_s(ms) == 12.5
    assert np.isnan(stream_span_s(iter(ms)))


def test_latency_histogram_percentiles_within_a_bin():
    rng = np.random.default_rng(0)
    x = rng.lognormal(np.log(2e-3), 0.8, 5000)
    h = LatencyHistogram()
    for v in x:
        h.add(float(v))
    for q in (50, 99):
        exact = float(np.percentile(x, q))
        assert exact <= h.percentile_s(q) <= exact * 1.13
    assert h.to_dict()["n"] == 5000 and h.to_dict()["max_ms"] == pytest.approx(1e3 * x.max())
    assert np.isnan(LatencyHistogram().percentile_s(99))


def test_corrupted_fixes_are_the_asked_share_moved_5_to_50_m():
    from fgslam.bench.wrong_fixes import corrupt_fixes
    from reloc.measurements import GlobalFix

    fixes = [GlobalFix(float(t), float(t) + 2.0, 1.0 * t, 0.0, 0.0, np.eye(3) * 0.01) for t in range(50)]
    out, wrong = corrupt_fixes(fixes, 0.2, seed=3)
    assert wrong.sum() == 10
    d = np.array([np.hypot(a.x_m - b.x_m, a.y_m - b.y_m) for a, b in zip(out, fixes)])
    assert np.all(d[~wrong] == 0.0) and np.all((d[wrong] >= 5.0) & (d[wrong] <= 50.0))
    assert np.array_equal(corrupt_fixes(fixes, 0.2, seed=3)[1], wrong)


def test_a_long_traverse_keeps_a_pose_a_second_and_the_truth_once():
    """What a long traverse keeps for its evaluation (the growth of `fgslam run`'s memory with
    distance): the online record and the EKF's history at 1 Hz, the truth at its own rate held
    once (no second copy in the runner); the same stream as a yard keeps every pose, and the two
    evaluations agree (one pose a second resolves the error)."""
    from fgslam.api import run_one
    from tests.fgslam._synth_stream import make_stream

    inputs = make_stream(seed=3, duration_s=60.0)
    yard = run_one(inputs, "ekf", False, CompareConfig())
    long = run_one(inputs, "ekf", False, CompareConfig(long_traverse=LongTraverseConfig(min_duration_s=30.0)))
    truth_t = np.array([m.t for m in inputs.measurements if type(m).__name__ == "GroundTruthPose"])

    assert np.median(np.diff(yard.result.online.t)) == pytest.approx(0.1, abs=1e-6)
    assert np.median(np.diff(long.result.online.t)) == pytest.approx(1.0, abs=0.04)  # 30 Hz steps
    assert np.median(np.diff(long.result.final.t)) == pytest.approx(1.0, abs=0.04)
    np.testing.assert_array_equal(long.gt.t, truth_t)  # evo pairs every pose with a truth stamp
    assert set(long.result.final.t) <= set(truth_t)
    assert yard.result.ground_truth is None and long.result.ground_truth is None  # the caller holds it
    assert long.used["runner"]["record_rate_hz"] == 1.0  # the config saved is the one used
    a, b = yard.metrics["ate"]["rmse"], long.metrics["ate"]["rmse"]
    assert abs(a - b) < 0.1 * a, (a, b)


def test_the_truth_built_block_by_block_is_the_stacked_truth():
    from scipy.spatial.transform import Rotation

    from fgslam.runner import ground_truth_trajectory
    from reloc.measurements import GroundTruthPose

    rng = np.random.default_rng(1)
    n = 9000  # over two blocks of rows
    pos, q = rng.normal(size=(n, 3)), Rotation.random(n, random_state=2).as_quat()
    gt = ground_truth_trajectory(GroundTruthPose(0.1 * k, pos[k], q[k]) for k in range(n))
    np.testing.assert_allclose(gt.t, 0.1 * np.arange(n))
    np.testing.assert_allclose(gt.T_world_base[:, :3, 3], pos)
    np.testing.assert_allclose(gt.T_world_base[:, :3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(gt.T_world_base[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
    assert ground_truth_trajectory([]) is None

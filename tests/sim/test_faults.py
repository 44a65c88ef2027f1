"""The fault models of ``SimConfig.faults``: config checks, and each fault's effect on what the
simulator writes (against the same seeded run without it; the truth is only changed by ``stuck``)."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from reloc.config import config_from_dict
from reloc.errors import ConfigError
from reloc.geometry import wrap_angle
from reloc.measurements import CmdVel, ImuSample, RockObservations, WheelOdometry
from sim import faults as F
from sim.config import SimConfig, TraverseConfig, validate
from sim.simulate import simulate

BASE = SimConfig(world="cnes", seed=2, traverse=TraverseConfig(distance_m=8.0))


@cache
def _run(name: str = "none"):
    faults = {
        "none": F.FaultsConfig(),
        "blackout": F.FaultsConfig(camera_blackout=F.CameraBlackout(start_s=10.0, duration_s=15.0)),
        "no_rocks": F.FaultsConfig(no_rocks=F.NoRocks(start_s=10.0, duration_s=15.0)),
        "imu": F.FaultsConfig(imu_bias_step=F.ImuBiasStep(start_s=10.0, duration_s=15.0)),
        "stuck": F.FaultsConfig(stuck=F.Stuck(start_s=10.0, duration_s=8.0)),
        "jitter": F.FaultsConfig(timestamp_jitter=F.TimestampJitter(jitter_s=0.02)),
    }[name]
    return simulate(dataclasses.replace(BASE, faults=faults))


def _of(run, kind):
    return [m for m in run.measurements if isinstance(m, kind)]


def test_faults_are_off_by_default_and_checked_by_key():
    assert SimConfig().faults.active() == {}
    cfg = config_from_dict(SimConfig, {"faults": {"camera_blackout": {"duration_s": 90}}})
    assert cfg.faults.camera_blackout == F.CameraBlackout(start_s=60.0, duration_s=90.0)
    bad = [({"camera_blackout": {"duration_s": -1}}, "faults.camera_blackout.duration_s"),
           ({"stuck": {"start_s": "soon"}}, "faults.stuck.start_s"),
           ({"timestamp_jitter": {"jitter_s": float("nan")}}, "faults.timestamp_jitter.jitter_s"),
           ({"blackout": {}}, "faults.blackout"),
           ({"imu_bias_step": {"gyro_radps": [0, 1]}}, "faults.imu_bias_step.gyro_radps"),
           ({"no_rocks": {"keep_false_positives": "no"}}, "faults.no_rocks.keep_false_positives")]
    for data, key in bad:
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            config_from_dict(SimConfig, {"faults": data})
    with pytest.raises(F.FaultConfigError, match="jitter_s must be < the fastest sensor period"):
        validate(dataclasses.replace(BASE, faults=F.FaultsConfig(timestamp_jitter=F.TimestampJitter(jitter_s=0.05))))
    with pytest.raises(F.FaultConfigError, match="kilometre"):
        validate(dataclasses.replace(BASE, world="plains-2km", faults=F.FaultsConfig(stuck=F.Stuck())))


def test_blackout_drops_frames_and_no_rocks_keeps_only_clutter():
    ref, black, empty = _run(), _run("blackout"), _run("no_rocks")
    np.testing.assert_array_equal(black.ground_truth.T_world_base, ref.ground_truth.T_world_base)
    t_ref = np.array([m.t for m in _of(ref, RockObservations)])
    t_black = np.array([m.t for m in _of(black, RockObservations)])
    a, b = black.stats["faults"]["camera_blackout"]
    assert (a, b) == (10.0, 25.0)
    np.testing.assert_array_equal(t_black, t_ref[(t_ref < a) | (t_ref >= b)])
    frames = _of(empty, RockObservations)
    assert len(frames) == len(t_ref) == len(empty.stereo_rock)
    inside = [(m, r) for m, r in zip(frames, empty.stereo_rock) if a <= m.t < b]
    assert len(inside) == 30 and sum(len(m.size_m) for m, _ in inside) > 0  # clutter stays
    assert all(np.all(r < 0) for _, r in inside)  # no true rock
    outside = [r for m, r in zip(frames, empty.stereo_rock) if not a <= m.t < b]
    assert sum(int(np.sum(r >= 0)) for r in outside) > 0


def test_imu_bias_step_offsets_rates_and_integrates_into_yaw():
    ref, imu = _of(_run(), ImuSample), _of(_run("imu"), ImuSample)
    step = F.ImuBiasStep()
    t = np.array([m.t for m in imu])
    d_gyro = np.array([m.gyro_radps for m in imu]) - np.array([m.gyro_radps for m in ref])
    d_acc = np.array([m.accel_mps2 for m in imu]) - np.array([m.accel_mps2 for m in ref])
    on = (t >= 10.0) & (t < 25.0)
    np.testing.assert_allclose(d_gyro[on], np.tile(step.gyro_radps, (on.sum(), 1)), atol=1e-12)
    np.testing.assert_allclose(d_gyro[~on], 0.0, atol=1e-12)
    np.testing.assert_allclose(d_acc[on], np.tile(step.accel_mps2, (on.sum(), 1)), atol=1e-12)
    yaw = lambda ms: Rotation.from_quat([m.quat_xyzw for m in ms]).as_euler("ZYX")[:, 0]
    d_yaw = wrap_angle(yaw(imu) - yaw(ref))
    expected = step.gyro_radps[2] * np.clip(t - 10.0, 0.0, 15.0)
    np.testing.assert_allclose(d_yaw, expected, atol=2e-3)
    assert d_yaw[-1] == pytest.approx(0.03, abs=2e-3)  # the heading error stays after the step


def test_stuck_truth_and_imu_stand_still_while_wheels_and_commands_drive():
    run = _run("stuck")
    a, b = run.stats["faults"]["stuck"]
    assert b - a == pytest.approx(8.0, abs=0.05) and a >= 10.0 - 1 / 30
    assert run.stats["duration_s"] == pytest.approx(_run().stats["duration_s"] + 8.0, abs=1e-6)
    t, p = run.ground_truth.t, run.ground_truth.positions_m
    stuck = (t >= a) & (t < b)
    assert np.ptp(p[stuck], axis=0).max() < 1e-9
    cmd, wheel, imu = _of(run, CmdVel), _of(run, WheelOdometry), _of(run, ImuSample)
    v_cmd = np.array([m.v_mps for m in cmd])[stuck]
    assert np.all(v_cmd > 0.05) and np.ptp(v_cmd) == 0.0
    assert np.all(np.array([m.v_mps for m in wheel])[stuck] > 0.05)
    gyro = np.array([m.gyro_radps for m in imu])[stuck][:-1]  # the last tick's rate reaches the moving pose after it
    assert np.abs(gyro).max() < 2e-3  # noise only: the IMU sees no turn
    acc = np.array([m.accel_mps2 for m in imu])[stuck][1:-1]
    assert np.std(acc[:, 0]) < 0.03  # white noise, 0.003 m/s^2/sqrt(Hz) at 30 Hz: no jolt


def test_jitter_is_bounded_keeps_each_topic_in_order_and_spares_the_truth():
    ref, jit = _run(), _run("jitter")
    np.testing.assert_array_equal(jit.ground_truth.t, ref.ground_truth.t)
    for kind in (CmdVel, ImuSample, WheelOdometry, RockObservations):
        t0 = np.array([m.t for m in _of(ref, kind)])
        t1 = np.array([m.t for m in _of(jit, kind)])
        d = t1 - t0
        assert d.min() >= 0.0 and d.max() <= 0.02 and d.std() > 0.003, kind.__name__
        assert np.all(np.diff(t1) > 0), kind.__name__

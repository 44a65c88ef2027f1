import numpy as np
import pytest
from hypothesis import given, strategies as st
from scipy.spatial.transform import Rotation

from reloc.config import config_from_dict, config_to_dict
from reloc.errors import ConfigError, MeasurementError
from reloc.measurements import CmdVel, GlobalFix, ImuSample, RockObservations, sort_key
from reloc.odometry import OdometryAssembler


def test_nan_rejected_with_field_name():
    with pytest.raises(MeasurementError, match="CmdVel.v_mps"):
        CmdVel(t=0.0, v_mps=float("nan"), yaw_rate_radps=0.0)
    with pytest.raises(MeasurementError, match="xyz_base_m"):
        RockObservations(0.0, [[np.nan, 0, 0]], [np.eye(3)], [0.3], [0.9])


def test_rock_observations_shapes_and_empty_frame():
    empty = RockObservations(1.0, np.zeros((0, 3)), np.zeros((0, 3, 3)), [], [])
    assert len(empty) == 0
    with pytest.raises(MeasurementError, match="cov_base_m2"):
        RockObservations(0.0, [[1, 0, 0]], [np.eye(3), np.eye(3)], [0.3], [0.9])
    with pytest.raises(MeasurementError, match="positive definite"):
        RockObservations(0.0, [[1, 0, 0]], [np.zeros((3, 3))], [0.3], [0.9])


def test_measurements_are_immutable_copies():
    xyz = np.array([[1.0, 2.0, 3.0]])
    obs = RockObservations(0.0, xyz, [np.eye(3)], [0.3], [0.9])
    xyz[0, 0] = 99.0
    assert obs.xyz_base_m[0, 0] == 1.0
    with pytest.raises(ValueError):
        obs.xyz_base_m[0, 0] = 5.0


def test_fix_validation():
    with pytest.raises(MeasurementError, match="t_recv"):
        GlobalFix(t_meas=5.0, t_recv=4.0, x_m=0, y_m=0, yaw_rad=0, cov_xyyaw=np.eye(3))
    with pytest.raises(MeasurementError, match="positive definite"):
        GlobalFix(t_meas=5.0, t_recv=6.0, x_m=0, y_m=0, yaw_rad=0, cov_xyyaw=np.zeros((3, 3)))


def test_a_fix_recorrelated_rescales_its_match_part_only():
    match = np.array([[0.04, 0.01, 0.001], [0.01, 0.09, -0.002], [0.001, -0.002, 0.0004]])
    rel = np.array([[0.02, 0.005], [0.005, 0.03]])
    cov = 6.0 * match
    cov[:2, :2] += rel
    fix = GlobalFix(1.0, 2.0, 3.0, 4.0, 0.5, cov, source="craters", correlation_scale=6.0, cov_relative_xy=rel)
    assert fix.recorrelated(6.0) is fix
    independent = fix.recorrelated(1.0)
    expect = match.copy()
    expect[:2, :2] += rel
    assert np.allclose(independent.cov_xyyaw, expect) and independent.correlation_scale == 1.0
    assert independent.source == "craters" and np.array_equal(independent.cov_relative_xy, rel)
    back = independent.recorrelated(6.0)
    assert np.allclose(back.cov_xyyaw, cov)
    no_rel = GlobalFix(1.0, 2.0, 3.0, 4.0, 0.5, match, correlation_scale=2.0)
    assert np.allclose(no_rel.recorrelated(8.0).cov_xyyaw, 4.0 * match)


def test_a_recorrelated_fix_carries_its_height_through_the_same_gradient():
    from reloc.measurements import FixHeight

    def with_height(cov, g=np.array([0.3, -0.2, 0.0]), sigma_dem=0.1):  # z read at the fix's (x, y)
        cz = cov @ g
        return FixHeight(5.0, sigma_dem**2 + float(g @ cz), cz)

    match = np.array([[0.04, 0.01, 0.001], [0.01, 0.09, -0.002], [0.001, -0.002, 0.0004]])
    fix = GlobalFix(1.0, 2.0, 3.0, 4.0, 0.5, 30.0 * match, height=with_height(30.0 * match), correlation_scale=30.0)
    again = fix.recorrelated(2.0)
    expect = with_height(2.0 * match)
    assert np.allclose(again.cov_xyyaw, 2.0 * match)
    assert again.height.var_m2 == pytest.approx(expect.var_m2) and np.allclose(again.height.cov_xyyaw, expect.cov_xyyaw)
    assert np.linalg.eigvalsh(again.cov)[0] > 0


@pytest.mark.parametrize("kwargs, message", [
    ({"correlation_scale": 0.5}, "correlation_scale must be >= 1"),
    ({"correlation_scale": float("nan")}, "correlation_scale is NaN"),
    ({"cov_relative_xy": np.array([[1.0, 0.0], [0.0, -1.0]])}, "cov_relative_xy must be symmetric positive semi-definite"),
    ({"cov_relative_xy": np.eye(3)}, "cov_relative_xy"),
    ({"source": 3}, "source must be a string"),
])
def test_fix_correlation_fields_are_checked(kwargs, message):
    with pytest.raises(MeasurementError, match=message):
        GlobalFix(1.0, 2.0, 3.0, 4.0, 0.5, np.eye(3) * 0.01, **kwargs)


def test_sort_key_puts_motion_before_rocks():
    obs = RockObservations(1.0, np.zeros((0, 3)), np.zeros((0, 3, 3)), [], [])
    imu = ImuSample(1.0, [0, 0, 0, 1])
    cmd = CmdVel(1.0, 0.1, 0.0)
    assert sorted([obs, imu, cmd], key=sort_key) == [cmd, imu, obs]


@given(st.floats(-np.pi, np.pi), st.floats(0.0, 0.5), st.floats(-0.3, 0.3))
def test_odometry_increment_recovers_rotation(yaw0, v, wz):
    asm = OdometryAssembler()
    R0 = Rotation.from_euler("zyx", [yaw0, 0.05, -0.02])
    R1 = R0 * Rotation.from_rotvec([0.0, 0.0, wz / 30.0])
    asm.push(CmdVel(0.0, v, wz))
    assert asm.push(ImuSample(0.0, R0.as_quat())) is None
    step = asm.push(ImuSample(1 / 30, R1.as_quat()))
    assert step is not None and step.v_mps == v
    np.testing.assert_allclose(step.dR_base, Rotation.from_rotvec([0, 0, wz / 30.0]).as_matrix(), atol=1e-9)


def test_odometry_rejects_out_of_order_and_duplicates():
    asm = OdometryAssembler()
    asm.push(ImuSample(1.0, [0, 0, 0, 1]))
    with pytest.raises(MeasurementError, match="older"):
        asm.push(CmdVel(0.5, 0.1, 0.0))
    with pytest.raises(MeasurementError, match="duplicate"):
        asm.push(ImuSample(1.0, [0, 0, 0, 1]))


def test_a_silent_speed_input_stops_the_rover_and_long_steps_integrate_every_command():
    """Issue 17, case 8: a command holds at most max_speed_age_s, so a bridged one-hour gap is
    not driven at the last speed; a step spanning a gap integrates the commands received in it."""
    q = [0, 0, 0, 1]
    asm = OdometryAssembler(max_gap_s=4000.0, max_speed_age_s=1.0)
    asm.push(CmdVel(0.0, 0.2, 0.01))
    asm.push(ImuSample(0.0, q))
    assert asm.push(ImuSample(0.5, q)).v_mps == 0.2  # a normal step: the latest command
    step = asm.push(ImuSample(0.75, q))  # the command (t = 0) expires at 1.0 s: still valid
    assert step.v_mps == 0.2
    step = asm.push(ImuSample(1.25, q))  # valid for half of this step
    assert step.v_mps == pytest.approx(0.1) and step.yaw_rate_cmd_radps == pytest.approx(0.005)
    step = asm.push(ImuSample(3601.25, q))
    assert step.v_mps * step.dt == 0.0  # an hour without commands: not 720 m
    for k in range(10):  # commands flowing through a long IMU gap: 0.1 m/s for 10 s, then stop
        asm.push(CmdVel(3602.0 + k, 0.1 if k < 9 else 0.0, 0.0))
    step = asm.push(ImuSample(3700.0, q))
    assert step.v_mps * step.dt == pytest.approx(0.9)
    a = OdometryAssembler()
    a.push(ImuSample(0.0, q))
    with pytest.raises(MeasurementError, match=r"IMU gap of 5.000 s .* limit of 1 s \(runner.max_imu_gap_s"):
        a.push(ImuSample(5.0, q))


def test_config_override_and_unknown_key():
    from dataclasses import dataclass, field

    @dataclass(frozen=True)
    class Inner:
        sigma_m: float = 0.1

    @dataclass(frozen=True)
    class Outer:
        rate_hz: float = 2.0
        inner: Inner = field(default_factory=Inner)

    cfg = config_from_dict(Outer, {"rate_hz": 5, "inner": {"sigma_m": 0.2}})
    assert cfg.rate_hz == 5.0 and cfg.inner.sigma_m == 0.2
    assert config_to_dict(cfg) == {"rate_hz": 5.0, "inner": {"sigma_m": 0.2}}
    with pytest.raises(ConfigError, match="bogus"):
        config_from_dict(Outer, {"bogus": 1})

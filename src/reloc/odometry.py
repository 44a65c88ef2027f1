"""Turn command-velocity and IMU samples into odometry steps that both back-ends consume.

A step spans two consecutive IMU samples. Its translation comes from the command velocity held
over the step (zero-order hold of the latest /cmd_vel, or wheel odometry when configured), its
rotation from the IMU orientation increment, which is far better than the commanded yaw rate.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np

from reloc.errors import MeasurementError
from reloc.measurements import CmdVel, ImuSample, WheelOdometry


def _quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w); cheaper than scipy for one sample."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class OdometryStep:
    """Motion of base_link between ``t0`` and ``t1``.

    ``v_mps``: forward speed (base_link x) over the step; ``yaw_rate_cmd_radps``: commanded yaw rate;
    ``R_ref_base0`` / ``R_ref_base1`` (3, 3): IMU orientations at t0 / t1 (gravity-aligned reference,
    yaw drifting); ``gyro_radps`` (3,): mean body rate; ``dR_base`` = R0.T @ R1 the body-frame
    rotation increment; ``extra_forward_var_m2``: forward translation variance (m^2) the back-ends
    add to their own noise over the step (the slip monitor's uncertainty, :mod:`reloc.slip`);
    ``extra_yaw_var_rad2``: heading variance (rad^2) about the gravity axis they add likewise (the
    gyro monitor's, :mod:`reloc.gyro`).
    """

    t0: float
    t1: float
    v_mps: float
    yaw_rate_cmd_radps: float
    R_ref_base0: np.ndarray
    R_ref_base1: np.ndarray
    gyro_radps: np.ndarray
    extra_forward_var_m2: float = 0.0
    extra_yaw_var_rad2: float = 0.0

    @property
    def dt(self) -> float:
        return self.t1 - self.t0

    @property
    def dR_base(self) -> np.ndarray:
        return self.R_ref_base0.T @ self.R_ref_base1


class OdometryAssembler:
    """Stateful: feed CmdVel / WheelOdometry / ImuSample in time order, get an OdometryStep per IMU sample.

    ``speed_source`` is "cmd" (the reference design) or "wheel" (use /wheel_odom when present).
    Steps longer than ``max_gap_s`` raise :class:`MeasurementError` (a gap in the IMU stream must
    be visible, not bridged silently). A speed input is held for at most ``max_speed_age_s`` after
    its stamp: the part of a step beyond that is not driven (a rover base stops when its commands
    stop), so a gap is never crossed at the last speed. A step longer than that (a gap bridged by
    a raised ``max_gap_s``) integrates every speed input received during it, each held from its
    stamp until the next one or its expiry; a normal step uses the latest speed throughout.
    """

    def __init__(self, speed_source: str = "cmd", max_gap_s: float = 1.0, max_speed_age_s: float = 1.0) -> None:
        if speed_source not in ("cmd", "wheel"):
            raise MeasurementError(f"speed_source must be 'cmd' or 'wheel', got {speed_source!r}")
        for name, value in (("max_gap_s", max_gap_s), ("max_speed_age_s", max_speed_age_s)):
            if not (math.isfinite(value) and value > 0):
                raise MeasurementError(f"OdometryAssembler {name} must be finite and > 0, got {value!r}")
        self.speed_source = speed_source
        self.max_gap_s = max_gap_s
        self.max_speed_age_s = max_speed_age_s
        self._v = 0.0
        self._w = 0.0
        self._speed_t = -np.inf  # stamp of the speed input held
        self._step_speeds: list[tuple[float, float, float]] = []  # (t, v, w) at the last IMU sample, then received since
        self._last_imu: ImuSample | None = None
        self._last_R: np.ndarray | None = None
        self._last_t = -np.inf

    def _check_time(self, t: float, what: str) -> None:
        if t < self._last_t:
            raise MeasurementError(f"{what} at t={t:.6f} s is older than the previous input ({self._last_t:.6f} s)")
        self._last_t = t

    def push(self, m: CmdVel | WheelOdometry | ImuSample) -> OdometryStep | None:
        """Consume one input; return the step completed by an IMU sample, else None."""
        self._check_time(m.t, type(m).__name__)
        if isinstance(m, (CmdVel, WheelOdometry)):
            if (self.speed_source == "cmd") == isinstance(m, CmdVel):
                self._v, self._w, self._speed_t = m.v_mps, m.yaw_rate_radps, m.t
                self._step_speeds.append((m.t, m.v_mps, m.yaw_rate_radps))
            return None
        if not isinstance(m, ImuSample):
            raise MeasurementError(f"OdometryAssembler cannot consume {type(m).__name__}")
        prev = self._last_imu
        if prev is not None:
            dt = m.t - prev.t
            if dt <= 0.0:
                raise MeasurementError(f"duplicate IMU stamp t={m.t:.6f} s")
            if dt > self.max_gap_s:
                raise MeasurementError(
                    f"IMU gap of {dt:.3f} s at t={m.t:.3f} s exceeds the limit of {self.max_gap_s:g} s "
                    "(runner.max_imu_gap_s in the --config file)"
                )
        # Each sample's rotation matrix is computed once and reused as the next step's start.
        R_prev, R_curr = self._last_R, _quat_xyzw_to_matrix(m.quat_xyzw)
        self._last_imu, self._last_R = m, R_curr
        speeds, self._step_speeds = self._step_speeds, [(self._speed_t, self._v, self._w)]
        if prev is None:
            return None
        v, w = self._step_speed(prev.t, m.t, speeds)
        return OdometryStep(
            t0=prev.t,
            t1=m.t,
            v_mps=v,
            yaw_rate_cmd_radps=w,
            R_ref_base0=R_prev,
            R_ref_base1=R_curr,
            gyro_radps=0.5 * (np.asarray(prev.gyro_radps) + np.asarray(m.gyro_radps)),
        )


    def _step_speed(self, t0: float, t1: float, speeds: list[tuple[float, float, float]]) -> tuple[float, float]:
        """Mean (v, yaw rate) over [t0, t1] from ``speeds`` = the input held at t0, then those received."""
        age, dt = self.max_speed_age_s, t1 - t0
        if dt <= age:  # the latest speed, for as much of the step as it is still valid
            held = min(max((self._speed_t + age - t0) / dt, 0.0), 1.0)
            return self._v * held, self._w * held
        dist = turn = 0.0
        for k, (ts, v, w) in enumerate(speeds):
            start = max(ts, t0)
            end = min(speeds[k + 1][0] if k + 1 < len(speeds) else t1, ts + age, t1)
            if end > start:
                dist, turn = dist + v * (end - start), turn + w * (end - start)
        return dist / dt, turn / dt


_E1 = np.array([1.0, 0.0, 0.0])


def step_translation(step: OdometryStep, dR: np.ndarray | None = None) -> np.ndarray:
    """Translation (3,) of base_link over ``step`` in its start frame: the commanded distance
    along the chord of the step's arc, the bisector of the start and end headings (``e1 + dR e1``),
    exact for a constant-curvature arc and free of trigonometry (this runs once per IMU sample).
    ``dR``: ``step.dR_base`` when already computed."""
    dR = step.dR_base if dR is None else dR
    chord = dR[:, 0] + _E1
    return chord * (step.v_mps * step.dt / max(float(np.sqrt(chord @ chord)), 1e-12))


def uphill_rad(step: OdometryStep) -> float:
    """Signed pitch (rad) of base_link x over the horizontal during ``step``, nose up positive
    (driving forward: uphill), the mean of its start and end (IMU gravity reference)."""
    s = 0.5 * (float(step.R_ref_base0[2, 0]) + float(step.R_ref_base1[2, 0]))
    return math.asin(min(max(s, -1.0), 1.0))


def pitch_rad(step: OdometryStep) -> float:
    """|pitch| (rad) of base_link x over the horizontal at the end of ``step`` (IMU gravity reference)."""
    return math.asin(min(abs(float(step.R_ref_base1[2, 0])), 1.0))

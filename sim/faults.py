"""Sensor faults injected into a yard run's measurements (``SimConfig.faults``, all off by default).

Each fault is a small seeded model with a time window ``[start_s, start_s + duration_s)`` in
seconds after the run's first sample (``duration_s`` None: to the end of the run). The faults change
what the simulator *writes*; the ground truth stays the rover's true motion:

- ``camera_blackout``: the stereo camera delivers no frame (no /rocks message) in the window;
- ``no_rocks``: frames keep coming but no true rock is in view: each frame keeps only its false
  detections (terrain clutter; ``keep_false_positives: false`` empties the frames);
- ``imu_bias_step``: a gyro and/or accelerometer bias step (body axes) in the window; the gyro's z
  step is integrated into the IMU's yaw (its heading is gyro-integrated), x/y only bias the rates
  (roll and pitch are held to gravity);
- ``stuck``: the rover is stuck for ``duration_s`` (100 % slip) at the first moving tick at or
  after ``start_s``: the truth and the IMU stand still, while /cmd_vel and /wheel_odom keep the
  command of the tick before (the wheels spin). The run gets ``duration_s`` longer;
- ``timestamp_jitter``: the recorder stamps /cmd_vel, /imu, /wheel_odom and /rocks on receipt,
  late by a bounded uniform delay in ``[0, jitter_s]``, drawn per message and topic; the bound must
  stay below the fastest sensor period, so each topic keeps its order (order preserved: the topics
  only interleave differently, nothing is left for the reader's reorder window); ground truth is
  not jittered;
- ``wrong_fixes``: not a sensor of the simulator (a bag holds no fixes): the fix source of
  ``fgslam bench faults`` (:class:`fgslam.fault_fixes.WrongFixes`) replaces every fix whose
  ``t_meas`` falls in the window (or a seeded ``fraction`` of them) by one ``offset_m`` off (or
  uniform up to ``offset_max_m``) in a seeded random direction and ``yaw_deg`` off in yaw,
  keeping the matcher's claimed covariance (a confidently wrong match).

Core maths only: no I/O.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.spatial.transform import Rotation

from reloc.config import Interval, NonNegative, Positive, checked
from sim.errors import SimError

FAULT_NAMES = ("camera_blackout", "no_rocks", "imu_bias_step", "stuck", "timestamp_jitter", "wrong_fixes")


class FaultConfigError(SimError, ValueError):
    """A fault's configuration is invalid (named by its key)."""


@checked(FaultConfigError)
@dataclass(frozen=True)
class CameraBlackout:
    """No stereo frame at all in the window."""

    start_s: NonNegative = 60.0
    duration_s: Positive | None = 120.0


@checked(FaultConfigError)
@dataclass(frozen=True)
class NoRocks:
    """Frames without any true rock in the window (only terrain clutter, or nothing)."""

    start_s: NonNegative = 60.0
    duration_s: Positive | None = 120.0
    keep_false_positives: bool = True


@checked(FaultConfigError)
@dataclass(frozen=True)
class ImuBiasStep:
    """Bias step added to the IMU's rates (rad/s, base_link) and specific force (m/s^2)."""

    start_s: NonNegative = 60.0
    duration_s: Positive | None = 120.0
    gyro_radps: tuple[float, float, float] = (0.0, 0.0, 0.002)  # z: about 0.11 deg/s (410 deg/h)
    accel_mps2: tuple[float, float, float] = (0.1, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("gyro_radps", "accel_mps2"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise FaultConfigError(f"faults.imu_bias_step.{name} must be 3 finite numbers, got {getattr(self, name)!r}")


@checked(FaultConfigError)
@dataclass(frozen=True)
class Stuck:
    """The rover stuck with spinning wheels for ``duration_s``."""

    start_s: NonNegative = 60.0
    duration_s: Positive = 60.0


@checked(FaultConfigError)
@dataclass(frozen=True)
class TimestampJitter:
    """Recorder stamp delay, uniform in [0, jitter_s] (bounded below the fastest sensor period)."""

    start_s: NonNegative = 0.0
    duration_s: Positive | None = None
    jitter_s: Positive = 0.01


@checked(FaultConfigError)
@dataclass(frozen=True)
class WrongFixesConfig:
    """Confidently wrong global fixes (applied by the fix source, see module doc): in the window,
    each fix is wrong with probability ``fraction`` (1: a burst, every one), moved ``offset_m``
    (or, with ``offset_max_m``, a distance uniform in [offset_m, offset_max_m]) in a random
    direction and turned ``yaw_deg``."""

    start_s: NonNegative = 60.0
    duration_s: Positive | None = 60.0
    offset_m: NonNegative = 3.0
    yaw_deg: NonNegative = 10.0
    fraction: Annotated[float, Interval(gt=0, le=1)] = 1.0
    offset_max_m: Positive | None = None

    def __post_init__(self) -> None:
        if self.offset_max_m is not None and self.offset_max_m < self.offset_m:
            raise FaultConfigError(f"wrong_fixes.offset_max_m ({self.offset_max_m}) is below offset_m ({self.offset_m})")


@dataclass(frozen=True)
class FaultsConfig:
    """The faults of a run; a None entry is off (the default)."""

    camera_blackout: CameraBlackout | None = None
    no_rocks: NoRocks | None = None
    imu_bias_step: ImuBiasStep | None = None
    stuck: Stuck | None = None
    timestamp_jitter: TimestampJitter | None = None
    wrong_fixes: WrongFixesConfig | None = None

    def active(self) -> dict:
        """Name -> config of the faults that are on."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}


def window_s(fault, t0_s: float, t_end_s: float) -> tuple[float, float]:
    """Absolute [start, end) of ``fault``'s window in a run spanning ``t0_s``..``t_end_s`` (s)."""
    start = t0_s + fault.start_s
    end = t_end_s + 1.0 if fault.duration_s is None else start + fault.duration_s
    return float(start), float(end)


def in_window(t: np.ndarray, window: tuple[float, float]) -> np.ndarray:
    """Mask (K,) of stamps ``t`` (K,) inside ``window`` = [start, end)."""
    t = np.asarray(t, float)
    return (t >= window[0]) & (t < window[1])


def validate_faults(faults: FaultsConfig, fastest_rate_hz: float, tiled: bool) -> None:
    """Cross-field rules the fault classes cannot check alone."""
    if tiled and faults.active():
        raise FaultConfigError("faults are for the yard presets and Gazebo worlds; the kilometre worlds take none")
    j = faults.timestamp_jitter
    if j is not None and not j.jitter_s < 1.0 / fastest_rate_hz:
        raise FaultConfigError(f"faults.timestamp_jitter.jitter_s must be < the fastest sensor period "
                               f"({1.0 / fastest_rate_hz:g} s), so that each topic keeps its order; got {j.jitter_s}")


def stuck_tick(speed_mps: np.ndarray, dt_s: float, stuck: Stuck) -> int:
    """The tick at which the rover gets stuck: the first moving tick at or after ``start_s``
    (``speed_mps`` (K,) the true planar speed per tick); -1 when it never moves again."""
    k0 = int(np.ceil(stuck.start_s / dt_s - 1e-9))
    moving = np.flatnonzero(np.asarray(speed_mps)[k0:] > 1e-4)
    return int(k0 + moving[0]) if moving.size else -1


def spin_commands(v_mps: np.ndarray, yaw_rate_radps: np.ndarray, k_from: int, k_to: int) -> tuple[np.ndarray, np.ndarray]:
    """Commands (K,) with ticks ``k_from .. k_to - 1`` (the truth standing still) holding the
    command of the last moving tick before them: the wheels keep turning."""
    v, w = np.array(v_mps, float), np.array(yaw_rate_radps, float)
    moving = np.flatnonzero((np.abs(v[:k_from]) > 1e-4) | (np.abs(w[:k_from]) > 1e-4))
    k_prev = int(moving[-1]) if moving.size else max(k_from - 1, 0)
    v[k_from:k_to] = v[k_prev]
    w[k_from:k_to] = w[k_prev]
    return v, w


def biased_imu(t_s: np.ndarray, dt_s: float, quat_xyzw: np.ndarray, gyro_radps: np.ndarray, accel_mps2: np.ndarray,
               step: ImuBiasStep, window: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU arrays (K, 4), (K, 3), (K, 3) with the bias step: rates and specific force offset in the
    window; the z rate offset integrated (rectangle rule, ``dt_s``) into the reported yaw from the
    window's start on (the heading error stays after the step ends, as a gyro-integrated yaw's would)."""
    on = in_window(t_s, window).astype(float)
    gyro = np.asarray(gyro_radps, float) + on[:, None] * np.asarray(step.gyro_radps, float)
    accel = np.asarray(accel_mps2, float) + on[:, None] * np.asarray(step.accel_mps2, float)
    dyaw = np.concatenate([[0.0], np.cumsum(on[:-1] * step.gyro_radps[2] * dt_s)])
    R = Rotation.from_rotvec(np.column_stack([np.zeros((len(dyaw), 2)), dyaw])) * Rotation.from_quat(quat_xyzw)
    return R.as_quat(), gyro, accel


def frame_masks(t_frames_s: np.ndarray, rock_rows: list[np.ndarray], faults: FaultsConfig, t0_s: float,
                t_end_s: float) -> list[np.ndarray | None]:
    """Per stereo frame: None (frame dropped: camera blackout) or the mask of its detections kept
    (a no-rocks stretch keeps the false ones, rows -1, or none)."""
    out: list[np.ndarray | None] = [np.ones(len(r), bool) for r in rock_rows]
    if faults.no_rocks is not None:
        nr = faults.no_rocks
        for i in np.flatnonzero(in_window(t_frames_s, window_s(nr, t0_s, t_end_s))):
            out[i] = (rock_rows[i] < 0) if nr.keep_false_positives else np.zeros(len(rock_rows[i]), bool)
    if faults.camera_blackout is not None:
        for i in np.flatnonzero(in_window(t_frames_s, window_s(faults.camera_blackout, t0_s, t_end_s))):
            out[i] = None
    return out


def jittered_stamps(t_s: np.ndarray, jitter: TimestampJitter, window: tuple[float, float],
                    rng: np.random.Generator) -> np.ndarray:
    """Stamps (K,) late by a uniform [0, jitter_s] delay on those inside the window."""
    t = np.asarray(t_s, float)
    err = rng.uniform(0.0, jitter.jitter_s, t.shape)
    return np.where(in_window(t, window), t + err, t)


def held_path(path, k_stuck: int, n_ticks: int):
    """``path`` (:class:`sim.rover.PlanarPath`) with the pose of tick ``k_stuck - 1`` held for
    ``n_ticks`` more ticks before tick ``k_stuck`` (the rover stuck there); stops after it shift."""
    k_prev = max(k_stuck - 1, 0)
    sel = np.concatenate([np.arange(k_stuck), np.full(n_ticks, k_prev), np.arange(k_stuck, len(path.x_m))])
    stops = np.where(path.stop_ticks >= k_stuck, path.stop_ticks + n_ticks, path.stop_ticks)
    return dataclasses.replace(path, x_m=path.x_m[sel], y_m=path.y_m[sel], yaw_rad=path.yaw_rad[sel],
                               stop_ticks=stops.astype(int))

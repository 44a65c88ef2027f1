"""A seeded synthetic measurement stream at the simulator's rates, for bag tests and benchmarks.

It has no physics: values are random but valid (unit quaternions, positive-definite
covariances), so that every field of every message type is exercised by a round trip, and bag
sizes and throughput are measured on streams of realistic rates and frame sizes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    Measurement,
    RockObservations,
    WheelOdometry,
    sort_key,
)


@dataclass(frozen=True)
class SyntheticStreamConfig:
    """Rates in Hz, duration in s; ``rocks_per_frame`` is the Poisson mean of detections."""

    duration_s: float = 10.0
    motion_rate_hz: float = 30.0  # cmd_vel, imu, ground truth, wheel odometry
    rock_rate_hz: float = 2.0
    rocks_per_frame: float = 15.0
    wheel_odom: bool = True
    ground_truth: bool = True
    empty_frame_every: int = 7  # every n-th rock frame is forced empty (0: never)


def _unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(0.0, 0.1, (n, 3, 3))
    return A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(3)


def synthetic_stream(config: SyntheticStreamConfig, rng: np.random.Generator) -> list[Measurement]:
    """A stream sorted by :func:`sort_key`; stamps are whole nanoseconds (exact in a bag)."""
    out: list[Measurement] = []
    n_motion = round(config.duration_s * config.motion_rate_hz)
    # t = ns / 1e9 with integer ns: exactly what a bag stamp reads back as.
    t_motion = (1_000_000_000 + np.round(np.arange(n_motion) * 1e9 / config.motion_rate_hz)) / 1e9
    quats = _unit_quats(rng, n_motion)
    for k, t in enumerate(t_motion):
        v, w = rng.normal(0.2, 0.05), rng.normal(0.0, 0.1)
        out.append(CmdVel(t, v, w))
        out.append(ImuSample(t, quats[k], rng.normal(0, 0.1, 3), rng.normal((0, 0, 9.81), 0.2)))
        if config.wheel_odom:
            out.append(WheelOdometry(t, v * rng.uniform(0.9, 1.0), w + rng.normal(0, 0.01)))
        if config.ground_truth:
            out.append(GroundTruthPose(t, rng.uniform(-40, 40, 3), _unit_quats(rng, 1)[0]))
    n_frames = round(config.duration_s * config.rock_rate_hz)
    for j in range(n_frames):
        t = (1_001_000_000 + round(j * 1e9 / config.rock_rate_hz)) / 1e9  # between motion samples
        empty = config.empty_frame_every and j % config.empty_frame_every == 0
        n = 0 if empty else int(rng.poisson(config.rocks_per_frame))
        out.append(
            RockObservations(
                t,
                rng.uniform((0.5, -5, -1), (10, 5, 1), (n, 3)),
                _spd(rng, n),
                rng.uniform(0.1, 1.5, n),
                rng.uniform(0.2, 1.0, n),
            )
        )
    out.sort(key=sort_key)
    return out

"""True body motion from a pose sequence, wheel slip, commanded velocity, and command-only dead
reckoning (command speed + IMU orientation, the way the back-ends predict)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.config import CmdConfig

log = logging.getLogger(__name__)


class OUProcess:
    """Stationary Ornstein-Uhlenbeck process (standard deviation ``sigma``, time constant ``tau_s``)
    sampled every ``dt_s``, chunk after chunk: ``sample(n)`` continues where the last call ended."""

    def __init__(self, dt_s: float, sigma: float, tau_s: float, rng: np.random.Generator) -> None:
        self.dt_s, self.sigma, self.tau_s, self.rng = dt_s, sigma, tau_s, rng
        self._last: float | None = None

    def sample(self, n: int) -> np.ndarray:
        """The next ``n`` samples."""
        from scipy.signal import lfilter

        if n == 0 or self.sigma == 0.0:
            return np.zeros(n)
        phi = np.exp(-self.dt_s / self.tau_s)
        e = self.rng.standard_normal(n) * self.sigma * np.sqrt(1.0 - phi**2)
        if self._last is None:
            e[0] = self.sigma * self.rng.standard_normal()
            x = lfilter([1.0], [1.0, -phi], e)
        else:
            x, _ = lfilter([1.0], [1.0, -phi], e, zi=[phi * self._last])
        self._last = float(x[-1])
        return x


def ou_process(n: int, dt_s: float, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary Ornstein-Uhlenbeck samples (n,) with standard deviation ``sigma`` and time constant ``tau_s``."""
    return OUProcess(dt_s, sigma, tau_s, rng).sample(n)


def body_rates(T_world_base: np.ndarray, dt_s: float, T_next: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed (K,) m/s along base x and body angular rate (K, 3) rad/s over each tick
    (forward differences; the last tick differences to ``T_next`` (4, 4) when given, else repeats
    the previous)."""
    if T_next is not None:
        v, w = body_rates(np.concatenate([T_world_base, T_next[None]]), dt_s)
        return v[:-1], w[:-1]
    p = T_world_base[:, :3, 3]
    R = T_world_base[:, :3, :3]
    dp = np.diff(p, axis=0)
    v = np.einsum("ki,ki->k", dp, R[:-1, :, 0]) / dt_s
    dR = np.einsum("kji,kjl->kil", R[:-1], R[1:])
    w = Rotation.from_matrix(dR).as_rotvec() / dt_s
    return np.append(v, v[-1:] if len(v) else [0.0]), np.vstack([w, w[-1:]]) if len(w) else np.zeros((1, 3))


def dead_reckon(p0_m: np.ndarray, R_ref_base: np.ndarray, v_mps: np.ndarray, dt_s: float) -> np.ndarray:
    """Positions (K, 3) from speed ``v_mps`` (K,) held over each tick along the x axis of the IMU
    orientation ``R_ref_base`` (K, 3, 3), starting at ``p0_m`` (3,)."""
    steps = R_ref_base[:, :, 0] * (v_mps * dt_s)[:, None]
    return np.vstack([p0_m, p0_m + np.cumsum(steps[:-1], axis=0)])


@dataclass(frozen=True)
class Commands:
    """Commanded velocity per tick: ``v_mps`` (K,), ``yaw_rate_radps`` (K,); the relative slip
    ``slip`` (K,) applied (cmd = true * (1 + slip)) and the solved slip ``gain``."""

    v_mps: np.ndarray
    yaw_rate_radps: np.ndarray
    slip: np.ndarray
    gain: float


class CommandModel:
    """Commanded velocity of a true motion, chunk after chunk (:meth:`step`); the slip and yaw
    errors are Ornstein-Uhlenbeck processes that carry over between chunks, the yaw-rate scale
    error is drawn once. A run in one chunk is :func:`make_commands`."""

    def __init__(self, cfg: CmdConfig, dt_s: float, rng: np.random.Generator) -> None:
        self.cfg, self.dt_s, self.rng = cfg, dt_s, rng
        self._slip = OUProcess(dt_s, cfg.slip_ou_sigma, cfg.slip_ou_tau_s, rng)
        self._yaw = OUProcess(dt_s, cfg.yaw_ou_sigma_radps, cfg.yaw_ou_tau_s, rng)
        self._scale: float | None = None

    def step(self, T_world_base: np.ndarray, R_imu: np.ndarray, T_next: np.ndarray | None = None,
             *, solve_gain: bool = False) -> Commands:
        """Commands for the true poses ``T_world_base`` (K, 4, 4) (``T_next``: the pose after the
        chunk, None at the end of the run). ``solve_gain`` (a whole run in one chunk only): solve
        the slip gain for ``cfg.target_drift_pct`` against the IMU orientation ``R_imu`` (K, 3, 3)."""
        cfg, dt_s = self.cfg, self.dt_s
        K = len(T_world_base)
        v_true, w_body = body_rates(T_world_base, dt_s, T_next)
        moving = (np.abs(v_true) > 1e-4) | (np.abs(w_body[:, 2]) > 1e-4)
        pitch_up = np.arcsin(np.clip(T_world_base[:, 2, 0], -1, 1))
        s = cfg.slip_mean + self._slip.sample(K) + cfg.slip_slope_gain * pitch_up
        gain = _solve_slip_gain(T_world_base, R_imu, v_true, s, dt_s, cfg) if solve_gain else 1.0
        slip = np.maximum(gain * s, -0.5)
        v_cmd = np.where(moving, v_true * (1.0 + slip), 0.0)
        if self._scale is None:
            self._scale = float(cfg.yaw_scale_sigma * self.rng.standard_normal())
        w_err = self._yaw.sample(K)
        w_cmd = np.where(moving, (w_body[:, 2] - w_err) / (1.0 + self._scale), 0.0)
        return Commands(v_cmd, w_cmd, slip, float(gain))


def make_commands(
    T_world_base: np.ndarray, R_imu: np.ndarray, dt_s: float, cfg: CmdConfig, rng: np.random.Generator
) -> Commands:
    """Commands whose slip-corrupted execution is the true motion ``T_world_base`` (K, 4, 4).

    With ``cfg.target_drift_pct`` the slip gain k is solved so that dead reckoning from the command
    speed and the IMU orientation ``R_imu`` (K, 3, 3) ends ``target_drift_pct`` % of the distance
    away (horizontally) from the true end point.
    """
    return CommandModel(cfg, dt_s, rng).step(T_world_base, R_imu, solve_gain=True)


def _solve_slip_gain(T_world_base, R_imu, v_true, s, dt_s, cfg: CmdConfig) -> float:
    """The slip gain k that puts command dead reckoning ``target_drift_pct`` % off (1 without a target)."""
    p_true = T_world_base[:, :3, 3]
    dist = float(np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=1)))
    gain = 1.0
    if cfg.target_drift_pct is not None and dist > 0:
        base = dead_reckon(p_true[0], R_imu, v_true, dt_s)[-1, :2] - p_true[-1, :2]
        a = np.sum((R_imu[:-1, :2, 0] * (v_true * s * dt_s)[:-1, None]), axis=0)
        target = cfg.target_drift_pct / 100.0 * dist
        qa, qb, qc = a @ a, 2 * a @ base, base @ base - target**2
        disc = qb**2 - 4 * qa * qc
        lo, hi = cfg.slip_gain_bounds
        if qa > 1e-12 and disc >= 0:
            gain = (-qb + np.sqrt(disc)) / (2 * qa)
        else:
            gain = hi
        if not lo <= gain <= hi:
            log.warning("slip gain %.3f for a %.2f %% drift is outside %s; clipped", gain, cfg.target_drift_pct, (lo, hi))
            gain = float(np.clip(gain, lo, hi))
    return gain

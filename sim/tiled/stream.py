"""The streaming simulator of the kilometre presets: drive, sense and write, one drive step at a
time, in bounded memory (no list of the traverse's measurements, no whole-traverse array).

``iter_measurements(cfg)`` yields the time-ordered measurements (the types of
:mod:`reloc.measurements`, as :func:`sim.simulate` returns them for the yards);
:class:`TiledSimulation` does the same and keeps the world, route and statistics;
:func:`sim.tiled.outputs.simulate_to_bag` writes a whole ``fgslam sim`` directory.
"""

from __future__ import annotations

import logging
import resource
from collections.abc import Callable, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from reloc.craters import CraterObservations
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    Measurement,
    RockObservations,
    WheelOdometry,
)
from sim.config import SimConfig, validate
from sim.rover import terrain_poses
from sim.sensors.craters import crater_bias, observe_craters
from sim.sensors.imu import ImuModel
from sim.sensors.motion import CommandModel
from sim.sensors.stereo import StereoBias, StereoCamera, calibration_error_base, simulate_stereo
from sim.tiled.drive import Driver
from sim.tiled.presets import resolve_tiled_config
from sim.tiled.route import revisits
from sim.tiled.world import TiledWorld

log = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb() -> float:
    """Resident memory of this process now (MB; /proc, else the peak)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        return peak_rss_mb()


def cpu_s() -> float:
    """CPU time (user + system) of this process so far, all threads (s)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class TiledSimulation:
    """A kilometre-preset run of ``cfg`` (built with :func:`sim.tiled.preset_config`).
    :meth:`measurements` may be consumed once; :attr:`stats` is complete after that."""

    def __init__(self, cfg: SimConfig, progress: Callable[[float], None] | None = None) -> None:
        validate(cfg)
        self.config = cfg = resolve_tiled_config(cfg)
        self.world = TiledWorld(cfg.world, cfg.seed, cfg.tiled)
        rngs = [np.random.default_rng([cfg.seed, 200 + k]) for k in range(6)]
        self.dt_s = 1.0 / cfg.sensors.imu.rate_hz
        self.driver = Driver(self.world, cfg, rngs[0])
        self._imu = ImuModel(cfg.sensors.imu, self.dt_s, rngs[1])
        self._cmd = CommandModel(cfg.sensors.cmd, self.dt_s, rngs[2])
        self._stereo_rng, self._wheel_rng = rngs[3], rngs[5]
        self._bias = StereoBias.draw(0, cfg.sensors.stereo, rngs[4])  # the run's mounting and scale errors
        self._frame_step = max(round(cfg.sensors.imu.rate_hz / cfg.sensors.stereo.rate_hz), 1)
        self._cam = StereoCamera.from_config(cfg.sensors.stereo)
        self._crater_rng = np.random.default_rng([cfg.seed, 300])  # its own stream: rocks' draws unchanged
        self._crater_step = max(round(cfg.sensors.imu.rate_hz / cfg.sensors.craters.rate_hz), 1)
        self._progress = progress
        self._used = False
        self._acc = {"distance_m": 0.0, "ticks": 0, "frames": 0, "visible": 0, "detections": 0, "true": 0,
                     "moving_ticks": 0, "slip_sum": 0.0, "windows": 0, "window_rocks": 0,
                     "crater_frames": 0, "crater_detections": 0, "crater_completeness_sum": 0.0}
        self._p_dr: np.ndarray | None = None  # command dead reckoning after the last tick
        self._dr_end = self._p_end = None  # reckoned and true position at the last tick
        self._imu_yaw_err = 0.0
        self.stats: dict = {}

    def measurements(self) -> Iterator[Measurement]:
        """The run's measurements in time order (:func:`reloc.measurements.sort_key`)."""
        if self._used:
            raise RuntimeError("TiledSimulation.measurements() can be consumed only once")
        self._used = True
        pending, tick, T_prev = None, 0, None
        n_max = max(round(self.config.tiled.chunk_s * self.config.sensors.imu.rate_hz), 2)
        for seg in self.driver.segments():
            T_seg = terrain_poses(seg.terrain, seg.path, self.config.rover)
            for k in range(0, len(T_seg), n_max):  # long stops come in bounded chunks
                T = T_seg[k:k + n_max]
                if pending is not None:
                    yield from self._sense(pending[0], pending[1], T_prev, T[0])
                    T_prev = pending[0][-1]
                pending = (T, tick)
                tick += len(T)
        yield from self._sense(pending[0], pending[1], T_prev, None)
        self._finish()

    # -- one chunk ------------------------------------------------------------------------------
    def _sense(self, T: np.ndarray, tick0: int, T_prev, T_next) -> list[Measurement]:
        cfg, dt = self.config, self.dt_s
        K = len(T)
        t = cfg.t_start_s + dt * (tick0 + np.arange(K))
        imu = self._imu.step(T, T_prev, T_next)
        cmd = self._cmd.step(T, imu.R_ref_base, T_next)
        quat_gt = Rotation.from_matrix(T[:, :3, :3]).as_quat()
        p = T[:, :3, 3]
        noise = 1.0 + cfg.sensors.wheel_speed_noise_rel * self._wheel_rng.standard_normal(K) if cfg.sensors.wheel_odometry else None
        first = (-tick0) % self._frame_step
        frames = np.arange(first, K, self._frame_step)
        rocks = dict(zip(frames.tolist(), self._stereo(T[frames], t[frames]))) if len(frames) else {}
        c_frames = np.arange((-tick0) % self._crater_step, K, self._crater_step)
        craters = dict(zip(c_frames.tolist(), self._craters(T[c_frames], t[c_frames]))) \
            if len(c_frames) and cfg.sensors.craters.enabled else {}
        # built in stream order (time, then reloc.measurements.KIND_ORDER): no sort needed
        meas: list[Measurement] = []
        v, w = cmd.v_mps.tolist(), cmd.yaw_rate_radps.tolist()
        for k in range(K):
            meas.append(CmdVel(t[k], v[k], w[k]))
            if noise is not None:
                meas.append(WheelOdometry(t[k], v[k] * noise[k], w[k]))
            meas.append(ImuSample(t[k], imu.quat_xyzw[k], imu.gyro_radps[k], imu.accel_mps2[k]))
            meas.append(GroundTruthPose(t[k], p[k], quat_gt[k]))
            if k in rocks:
                meas.append(rocks[k])
            if k in craters:
                meas.append(craters[k])
        self._account(T, p, imu, cmd, T_prev)
        if self._progress is not None:
            self._progress(self._acc["distance_m"])
        return meas

    def _stereo(self, T_frames: np.ndarray, t_frames: np.ndarray) -> list[RockObservations]:
        cfg = self.config.sensors.stereo
        cam_xy = (T_frames @ self._cam.T_base_cam)[:, :2, 3]
        m = self.config.tiled.sensor_window_margin_m
        window = self.world.local_world((cam_xy[:, 0].min() - m, cam_xy[:, 0].max() + m,
                                         cam_xy[:, 1].min() - m, cam_xy[:, 1].max() + m))
        bias = StereoBias(cfg.centre_error_frac * window.shape_error, self._bias.R_cam_err, self._bias.depth_scale)
        st = simulate_stereo(window.world, T_frames, cfg, self._stereo_rng, bias=bias)
        a = self._acc
        a["frames"] += len(T_frames)
        a["visible"] += st.n_visible
        a["detections"] += st.n_detections
        a["true"] += st.n_true
        a["windows"] += 1
        a["window_rocks"] += len(window.world.rocks)
        return [RockObservations(t_frames[i], st.xyz_base_m[i], st.cov_base_m2[i], st.size_m[i], st.score[i])
                for i in range(len(T_frames))]

    def _craters(self, T_frames: np.ndarray, t_frames: np.ndarray) -> list[CraterObservations]:
        """Crater rims of the frames at ``T_frames`` (F, 4, 4) (:mod:`sim.sensors.craters`)."""
        cc, st = self.config.sensors.craters, self.config.sensors.stereo
        xy = (T_frames @ self._cam.T_base_cam)[:, :2, 3]
        r = cc.max_range_m
        found = self.world.craters_near((xy[:, 0].min() - r, xy[:, 0].max() + r, xy[:, 1].min() - r,
                                         xy[:, 1].max() + r), reach_radii=1.0, d_min_m=cc.min_diameter_m)
        a = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
        rim = found.xy_m[:, None, :] + 0.5 * found.diameter_m[:, None, None] * np.stack([np.cos(a), np.sin(a)], 1)
        rim_z = self.world.height_at(rim.reshape(-1, 2)).reshape(len(found), 16).mean(axis=1) if len(found) \
            else np.zeros(0)
        bias_dir = crater_bias(self.config.seed, found.id)
        out = []
        for T, t in zip(T_frames, t_frames):
            obs, _ = observe_craters(found, rim_z, T, float(t), cc, st, self._cam, self._bias, bias_dir,
                                     self._crater_rng)
            out.append(obs)
        a = self._acc
        a["crater_frames"] += len(out)
        a["crater_detections"] += sum(len(o) for o in out)
        a["crater_completeness_sum"] += float(sum(o.completeness.sum() for o in out))
        return out

    def _account(self, T, p, imu, cmd, T_prev) -> None:
        a, dt = self._acc, self.dt_s
        q = p if T_prev is None else np.vstack([T_prev[:3, 3], p])
        a["distance_m"] += float(np.sum(np.linalg.norm(np.diff(q, axis=0), axis=1)))
        a["ticks"] += len(p)
        moving = np.abs(cmd.v_mps) > 1e-4
        a["moving_ticks"] += int(moving.sum())
        a["slip_sum"] += float(cmd.slip[moving].sum())
        # command-only dead reckoning, as the back-ends predict (sim.sensors.motion.dead_reckon)
        steps = imu.R_ref_base[:, :, 0] * (cmd.v_mps * dt)[:, None]
        start = p[0] if self._p_dr is None else self._p_dr
        self._p_dr = start + steps.sum(axis=0)
        self._dr_end = start + steps[:-1].sum(axis=0)  # the position reckoned for the chunk's last tick
        self._p_end = p[-1]
        self._imu_yaw_err = float(imu.yaw_error_rad[-1])

    def _finish(self) -> None:
        a, cfg = self._acc, self.config
        dist = a["distance_m"]
        duration = (a["ticks"] - 1) * self.dt_s
        w, scale = calibration_error_base(self._bias, self._cam)
        self.stats = {
            "world": cfg.world,
            "seed": cfg.seed,
            "distance_m": dist,
            "duration_s": duration,
            "mean_speed_mps": dist / max(duration, 1e-9),
            "drift_pct": 100.0 * float(np.linalg.norm(self._dr_end[:2] - self._p_end[:2])) / max(dist, 1e-9),
            "slip_mean": a["slip_sum"] / max(a["moving_ticks"], 1),
            "imu_final_yaw_error_deg": float(np.rad2deg(self._imu_yaw_err)),
            "cruise_speed_mps": cfg.rover.cruise_speed_mps,
            "n_stereo_frames": a["frames"],
            "n_visible": a["visible"],
            "n_detections": a["detections"],
            "stereo_precision": a["true"] / max(a["detections"], 1),
            "stereo_recall": a["true"] / max(a["visible"], 1),
            "stereo_rotation_error_deg": [round(float(x), 5) for x in np.degrees(w)],
            "stereo_depth_scale": round(float(scale), 6),
            "n_strategic_waypoints": len(self.driver.route),
            "n_drive_steps": self.driver.n_steps,
            "n_stops": self.driver.n_stops,
            "n_revisit_relaxed": self.driver.planner.n_relaxed,
            "n_revisits": revisits(self.driver.planner.history_t, self.driver.planner.history_xy,
                                   cfg.tiled.route.revisit_radius_m, cfg.tiled.route.revisit_after_s),
            "tiles_generated": self.world.tiles_made,
            "mean_window_rocks": a["window_rocks"] / max(a["windows"], 1),
            "n_crater_frames": a["crater_frames"],
            "n_crater_detections": a["crater_detections"],
            "crater_mean_completeness": a["crater_completeness_sum"] / max(a["crater_detections"], 1),
            "peak_rss_mb_after_drive": round(peak_rss_mb(), 1),
        }
        log.info("simulated %s seed %d: %.1f m in %.1f s, command dead-reckoning drift %.2f %%", cfg.world,
                 cfg.seed, dist, duration, self.stats["drift_pct"])


def iter_measurements(cfg: SimConfig) -> Iterator[Measurement]:
    """The time-ordered measurements of a kilometre-preset run, generated as they are consumed."""
    return TiledSimulation(cfg).measurements()

"""The simulator composer: world -> route -> rover motion -> sensors -> time-ordered measurements."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from reloc.backend import PoseEstimate, Trajectory, known_start_cov
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    Measurement,
    RockCatalog,
    RockObservations,
    WheelOdometry,
    sort_key,
)
from sim import faults as F
from sim.config import SimConfig, SimConfigError, resolve_orbital, validate
from sim.rocks import Rocks
from sim.route import plan_route
from sim.rover import drive_route, insert_pauses, terrain_poses
from sim.sensors.imu import simulate_imu
from sim.sensors.motion import dead_reckon, make_commands
from sim.sensors.orbital import simulate_catalog
from sim.sensors.stereo import StereoCamera, calibration_error_base, simulate_stereo
from sim.world import IMPORTED_MEAN_SPEED_MPS, IMPORTED_TRAVERSE_M, World, build_world

log = logging.getLogger(__name__)

INITIAL_POSE_COV = known_start_cov()  # m^2 and rad^2: as for a bag's start pose (a run in memory and its bag agree)


@dataclass
class SimRun:
    """Everything a run produced; ``measurements`` sorted by :func:`reloc.measurements.sort_key`."""

    config: SimConfig
    world: World
    measurements: list[Measurement]
    ground_truth: Trajectory
    initial_pose: PoseEstimate
    catalog: RockCatalog
    catalog_rock: np.ndarray  # per catalog entry: true rock row, -1 for a false positive
    rocks_true: Rocks
    stats: dict
    stereo_rock: list[np.ndarray]  # per stereo frame: true rock row of each detection (-1 false)
    stereo_visible: list[np.ndarray]  # per stereo frame: rows of the visible rocks


def resolve_config(cfg: SimConfig, world: World) -> SimConfig:
    """``cfg`` with every preset-dependent ``None`` filled in for ``world``."""
    p = world.preset
    distance = cfg.traverse.distance_m or (p.traverse_m if p else IMPORTED_TRAVERSE_M)
    mean_speed = p.mean_speed_mps if p else IMPORTED_MEAN_SPEED_MPS
    duration = cfg.traverse.duration_s or distance / mean_speed
    cruise = cfg.rover.cruise_speed_mps or min(1.25 * distance / duration, cfg.rover.max_speed_mps)
    n_rocks = cfg.worldgen.n_rocks if cfg.worldgen.n_rocks is not None else len(world.rocks)
    return dataclasses.replace(
        cfg,
        worldgen=dataclasses.replace(cfg.worldgen, n_rocks=n_rocks),
        traverse=dataclasses.replace(cfg.traverse, distance_m=float(distance), duration_s=float(duration)),
        rover=dataclasses.replace(cfg.rover, cruise_speed_mps=float(cruise)),
        sensors=dataclasses.replace(cfg.sensors, orbital=resolve_orbital(cfg.sensors.orbital)),
    )


def _drive(world: World, cfg: SimConfig, rng: np.random.Generator):
    """Planar path stretched by pauses to the configured duration; the cruise speed is raised if
    driving and turning alone would take longer."""
    tr, rv = cfg.traverse, cfg.rover
    dt = 1.0 / cfg.sensors.imu.rate_hz
    route = plan_route(world, 1.15 * tr.distance_m + 10.0, tr, rng)  # pure pursuit cuts corners
    start_ticks = round(tr.start_pause_s / dt)
    total_ticks = round(tr.duration_s / dt) + 1
    v = rv.cruise_speed_mps
    for _ in range(6):
        path = drive_route(world.terrain, route, tr.distance_m, v, rv, dt)
        fill = total_ticks - start_ticks - len(path.x_m)
        if fill >= 0 or v >= rv.max_speed_mps:
            break
        v = min(v * 1.15 * len(path.x_m) / max(total_ticks - start_ticks, 1), rv.max_speed_mps)
    if fill < 0:
        log.warning("traverse needs %.1f s at the maximum speed, more than the %.1f s asked",
                    (len(path.x_m) + start_ticks) * dt, tr.duration_s)
    return route, insert_pauses(path, max(fill, 0), start_ticks), v


def simulate(cfg: SimConfig) -> SimRun:
    """Run the simulator for ``cfg``; see :class:`SimRun` for what comes back."""
    validate(cfg)
    world = build_world(cfg.world, cfg.seed, cfg.worldgen)
    cfg = resolve_config(cfg, world)
    rngs = [np.random.default_rng([cfg.seed, 100 + k]) for k in range(7)]
    route, path, cruise = _drive(world, cfg, rngs[0])
    cfg = dataclasses.replace(cfg, rover=dataclasses.replace(cfg.rover, cruise_speed_mps=float(cruise)))
    dt = path.dt_s
    faults = cfg.faults
    k_stuck, n_stuck = -1, 0
    if faults.stuck is not None:  # the truth stands still: held before the poses are built
        speed = np.hypot(np.diff(path.x_m, prepend=path.x_m[0]), np.diff(path.y_m, prepend=path.y_m[0])) / dt
        k_stuck = F.stuck_tick(speed, dt, faults.stuck)
        if k_stuck < 0:
            raise SimConfigError(f"faults.stuck.start_s {faults.stuck.start_s} s: the rover does not move after it")
        n_stuck = round(faults.stuck.duration_s / dt)
        path = F.held_path(path, k_stuck, n_stuck)
    T = terrain_poses(world.terrain, path, cfg.rover)
    K = len(T)
    t = cfg.t_start_s + dt * np.arange(K)
    imu = simulate_imu(T, dt, cfg.sensors.imu, rngs[1])
    cmd = make_commands(T, imu.R_ref_base, dt, cfg.sensors.cmd, rngs[2])
    step = max(round(cfg.sensors.imu.rate_hz / cfg.sensors.stereo.rate_hz), 1)
    frame_ticks = np.arange(0, K, step)
    stereo = simulate_stereo(world, T[frame_ticks], cfg.sensors.stereo, rngs[3])
    cat = simulate_catalog(world, cfg.sensors.orbital, rngs[4])

    windows = {name: F.window_s(f, t[0], t[-1]) for name, f in faults.active().items()}
    v_cmd, w_cmd = cmd.v_mps, cmd.yaw_rate_radps
    if k_stuck >= 0:  # ticks k_stuck - 1 .. k_stuck + n_stuck - 1 share one true pose
        windows["stuck"] = (float(t[k_stuck - 1]), float(t[k_stuck + n_stuck]))
        v_cmd, w_cmd = F.spin_commands(v_cmd, w_cmd, k_stuck - 1, k_stuck + n_stuck)
    quat_imu, gyro, accel = imu.quat_xyzw, imu.gyro_radps, imu.accel_mps2
    if faults.imu_bias_step is not None:
        quat_imu, gyro, accel = F.biased_imu(t, dt, quat_imu, gyro, accel, faults.imu_bias_step, windows["imu_bias_step"])
    keep = F.frame_masks(t[frame_ticks], stereo.rock, faults, t[0], t[-1])
    stamps = {name: t for name in ("cmd", "imu", "wheel")} | {"rocks": t[frame_ticks]}
    if faults.timestamp_jitter is not None:  # each topic's recorder clock on its own draw
        stamps = {name: F.jittered_stamps(ts, faults.timestamp_jitter, windows["timestamp_jitter"], rngs[6])
                  for name, ts in stamps.items()}

    meas: list[Measurement] = []
    quat_gt = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    for k in range(K):
        meas.append(CmdVel(stamps["cmd"][k], v_cmd[k], w_cmd[k]))
        meas.append(ImuSample(stamps["imu"][k], quat_imu[k], gyro[k], accel[k]))
        meas.append(GroundTruthPose(t[k], T[k, :3, 3], quat_gt[k]))
    if cfg.sensors.wheel_odometry:
        noise = 1.0 + cfg.sensors.wheel_speed_noise_rel * rngs[5].standard_normal(K)
        for k in range(K):
            meas.append(WheelOdometry(stamps["wheel"][k], v_cmd[k] * noise[k], w_cmd[k]))
    no_rocks = (F.in_window(t[frame_ticks], windows["no_rocks"]) if "no_rocks" in windows
                else np.zeros(len(frame_ticks), bool))
    stereo_rock, stereo_visible = [], []
    for i, k in enumerate(frame_ticks):
        m = keep[i]
        if m is None:  # camera blackout: no frame
            continue
        meas.append(RockObservations(stamps["rocks"][i], stereo.xyz_base_m[i][m], stereo.cov_base_m2[i][m],
                                     stereo.size_m[i][m], stereo.score[i][m]))
        stereo_rock.append(stereo.rock[i][m])
        stereo_visible.append(stereo.visible[i][:0] if no_rocks[i] else stereo.visible[i])
    meas.sort(key=sort_key)

    p = T[:, :3, 3]
    distance = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    dr = dead_reckon(p[0], imu.R_ref_base, cmd.v_mps, dt)
    n_cat_true = int(np.sum(cat.rock >= 0))
    stats = {
        "world": world.name,
        "seed": cfg.seed,
        "distance_m": distance,
        "duration_s": float(t[-1] - t[0]),
        "drift_pct": 100.0 * float(np.linalg.norm(dr[-1, :2] - p[-1, :2])) / max(distance, 1e-9),
        "slip_gain": cmd.gain,
        "slip_mean": float(np.mean(cmd.slip[np.abs(cmd.v_mps) > 1e-4])) if np.any(np.abs(cmd.v_mps) > 1e-4) else 0.0,
        "imu_final_yaw_error_deg": float(np.rad2deg(imu.yaw_error_rad[-1])),
        "cruise_speed_mps": float(cruise),
        "n_stereo_frames": len(stereo_rock),
        "n_visible": stereo.n_visible,
        "n_detections": stereo.n_detections,
        "stereo_precision": stereo.n_true / max(stereo.n_detections, 1),
        "stereo_recall": stereo.n_true / max(stereo.n_visible, 1),
        **_stereo_error_stats(stereo, cfg.sensors.stereo),
        "n_rocks": len(world.rocks),
        "n_catalog": len(cat.catalog),
        "catalog_precision": n_cat_true / max(len(cat.catalog), 1),
        "catalog_recall": n_cat_true / max(len(world.rocks), 1),
        "n_route_waypoints": len(route),
        "n_measurements": len(meas),
    }
    if windows:
        stats["faults"] = {name: [float(a), float(min(b, t[-1]))] for name, (a, b) in windows.items()}
    log.info("simulated %s seed %d: %.1f m in %.1f s, drift %.2f %%", world.name, cfg.seed,
             distance, stats["duration_s"], stats["drift_pct"])
    return SimRun(
        config=cfg,
        world=world,
        measurements=meas,
        ground_truth=Trajectory(t=t, T_world_base=T),
        initial_pose=PoseEstimate(t=float(t[0]), T_world_base=T[0].copy(), cov=INITIAL_POSE_COV.copy()),
        catalog=cat.catalog,
        catalog_rock=cat.rock,
        rocks_true=world.rocks,
        stats=stats,
        stereo_rock=stereo_rock,
        stereo_visible=stereo_visible,
    )


def _stereo_error_stats(stereo, cfg) -> dict:
    """The run's drawn stereo calibration errors (what a back-end's calibration should find)."""
    if stereo.bias is None:
        return {}
    w, scale = calibration_error_base(stereo.bias, StereoCamera.from_config(cfg))
    return {"stereo_rotation_error_deg": [round(float(x), 5) for x in np.degrees(w)],
            "stereo_depth_scale": round(float(scale), 6)}

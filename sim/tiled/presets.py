"""The kilometre presets and their configuration.

| preset | world | rocks k | surface age | relief (512 m octave) | default traverse |
| plains-2km | 2.4 km | 5 % | 0.3 Gyr (moderate craters) | 8 m | 2 km |
| rocky-1km | 1.4 km | 15 % | 0.5 Gyr | 10 m | 1 km |
| cratered-3km | 3.2 km | 3 % (few rocks) | 3.0 Gyr (saturated below ~100 m) | 6 m | 3 km |
| sparse-5km | 5 km | 2 % | 0.01 Gyr (young: few craters) | 6 m | 5 km |

Their defaults differ from a yard run's: realistic stereo errors on (the systematic terms of
docs/sim.md: centre error 0.25 radii, mounting 0.15 deg, range scale 0.003), no drift target (drift
is what the slip, IMU and stereo models give), a tactical-grade gyro (1 deg/h bias, MER's LN-200
class), the orbital catalog at HiRISE resolution (0.25 m/px,
rocks under 3 px never found, recall counted over the detectable rocks), and a cruise speed of
0.12 m/s (the yard presets' mean speeds are 0.07-0.14 m/s; with stops and turns the mean comes out
near 0.1 m/s).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from reloc.config import config_from_dict
from sim.config import SimConfig, SimConfigError, resolve_orbital

KM_CRUISE_SPEED_MPS = 0.12
REALISTIC_STEREO = {"centre_error_frac": 0.25, "extrinsic_sigma_deg": 0.15, "depth_scale_sigma": 0.003}
HIRISE_CATALOG = {"gsd_m": 0.25, "min_size_px": 3.0, "recall_basis": "detectable"}
# A tactical-grade (LN-200 class, the MER rovers' IMU) gyro: 1 deg/h bias, rate random walk
# 0.05 deg/h/sqrt(h). The yards' 2e-7 rad/s/sqrt(s) walk is harmless over 15 minutes but alone
# turns the yaw by ~57 deg in 12 hours: not a real rover IMU.
TACTICAL_GYRO = {"gyro_bias_sigma_radps": 4.85e-6, "gyro_bias_walk_radps_rsqrt_s": 4.0e-9}


@dataclass(frozen=True)
class TiledPreset:
    name: str
    size_m: float
    rock_k: float
    crater_age_gyr: float
    relief_m: float
    hurst: float
    traverse_m: float
    summary: str
    # few landmarks along the route (a young surface, few rocks): the smoother gets the model of
    # docs/smoother.md "The heading and the distance on sparse ground" (backend_calibration)
    sparse_ground: bool = False


TILED_PRESETS: dict[str, TiledPreset] = {
    p.name: p
    for p in (
        TiledPreset("plains-2km", 2400.0, 0.05, 0.3, 8.0, 0.9, 2000.0, "plains, k 5 %, moderate craters"),
        TiledPreset("rocky-1km", 1400.0, 0.15, 0.5, 10.0, 0.85, 1000.0, "rock field, k 15 %"),
        TiledPreset("cratered-3km", 3200.0, 0.03, 3.0, 6.0, 0.9, 3000.0, "dense small craters, few rocks"),
        TiledPreset("sparse-5km", 5000.0, 0.02, 0.01, 6.0, 0.95, 5000.0, "k 2 %, few craters: the hard case",
                    sparse_ground=True),
    )
}


def is_tiled(world: str) -> bool:
    return world in TILED_PRESETS


def preset_overrides(name: str) -> dict:
    """The preset's configuration as a YAML-shaped mapping over :class:`sim.config.SimConfig`."""
    if name not in TILED_PRESETS:
        raise SimConfigError(f"unknown kilometre preset {name!r}: use one of {sorted(TILED_PRESETS)}")
    p = TILED_PRESETS[name]
    return {
        "world": name,
        "traverse": {"distance_m": p.traverse_m},
        "rover": {"cruise_speed_mps": KM_CRUISE_SPEED_MPS},
        "sensors": {"cmd": {"target_drift_pct": None}, "stereo": dict(REALISTIC_STEREO), "orbital": dict(HIRISE_CATALOG),
                    "imu": dict(TACTICAL_GYRO)},
        "tiled": {"terrain": {"relief_m": p.relief_m, "hurst": p.hurst}, "rocks": {"k": p.rock_k},
                  "craters": {"age_gyr": p.crater_age_gyr}},
    }


def preset_config(name: str, seed: int = 0, overrides: dict | None = None) -> SimConfig:
    """The :class:`SimConfig` of kilometre preset ``name`` with ``overrides`` (a YAML-shaped
    mapping, unknown keys rejected) on top."""
    cfg = config_from_dict(SimConfig, preset_overrides(name))
    cfg = config_from_dict(SimConfig, overrides or {}, base=cfg)
    return dataclasses.replace(cfg, world=name, seed=int(seed))


def resolve_tiled_config(cfg: SimConfig) -> SimConfig:
    """``cfg`` with every preset-dependent ``None`` filled in; the world grows (side x sqrt of the
    length ratio) for traverses longer than the preset's. Rejects what the streaming path cannot do."""
    if cfg.world not in TILED_PRESETS:
        raise SimConfigError(f"{cfg.world!r} is not a kilometre preset ({sorted(TILED_PRESETS)})")
    p = TILED_PRESETS[cfg.world]
    if cfg.sensors.cmd.target_drift_pct is not None:
        raise SimConfigError("sensors.cmd.target_drift_pct must be null on the kilometre presets: drift is what the "
                             "models give (build the config with sim.tiled.preset_config)")
    if cfg.traverse.duration_s is not None:
        raise SimConfigError("traverse.duration_s must be null on the kilometre presets: the duration is what the "
                             "drive takes (set rover.cruise_speed_mps or tiled.route.stop_s instead)")
    distance = cfg.traverse.distance_m or p.traverse_m
    t = cfg.tiled
    size = t.size_m or p.size_m * max(1.0, math.sqrt(distance / p.traverse_m))
    tiled = dataclasses.replace(
        t, size_m=float(size),
        terrain=dataclasses.replace(t.terrain, relief_m=t.terrain.relief_m if t.terrain.relief_m is not None else p.relief_m,
                                    hurst=t.terrain.hurst if t.terrain.hurst is not None else p.hurst),
        rocks=dataclasses.replace(t.rocks, k=t.rocks.k if t.rocks.k is not None else p.rock_k),
        craters=dataclasses.replace(t.craters, age_gyr=t.craters.age_gyr if t.craters.age_gyr is not None else p.crater_age_gyr),
    )
    return dataclasses.replace(
        cfg, tiled=tiled,
        traverse=dataclasses.replace(cfg.traverse, distance_m=float(distance)),
        rover=dataclasses.replace(cfg.rover, cruise_speed_mps=float(cfg.rover.cruise_speed_mps or KM_CRUISE_SPEED_MPS)),
        sensors=dataclasses.replace(cfg.sensors, orbital=resolve_orbital(cfg.sensors.orbital)),
    )


def relocalizer_calibration(cfg: SimConfig) -> dict:
    """The ``relocalizer`` block that sizes the rock matcher to this run's catalog: its per-axis
    sigma between local map and catalog is the catalog's position error, ``sigma_position_px``
    ground samples (the published detector: 2 px, 0.5 m at 0.25 m/px). The matcher's default
    (0.1 m) is 2 px of the yards' 5 cm images; at HiRISE resolution true pairs lie 5x outside it
    and no triangle of them can vote (docs/sim.md, "Rock fixes at orbital scale")."""
    det = resolve_orbital(cfg.sensors.orbital)
    return {"matcher": {"sigma_m": round(float(det.gsd_m * det.sigma_position_px), 6)}}


# the span (s) over which the smoother takes the gyro bias as white noise: with the bias over 120 s
# (the fixed-lag window) rocky-1km's first 400 m were optimistic (position NEES 2.9), over 300 s not
ISAM2_BIAS_HORIZON_S = 300.0


def backend_calibration(cfg: SimConfig) -> dict:
    """The ``backend_overrides`` block the back-ends need for this run's sensors, as a datasheet
    gives them: the stereo calibration states of docs/ekf.md and docs/smoother.md sized by the
    simulated errors, the IMU's gyro bias figures for the EKF's yaw-rate bias state, and the
    smoother's odometry rotation noise from the gyro."""
    st, imu = cfg.sensors.stereo, cfg.sensors.imu
    ekf: dict = {"yaw_rate_bias_sigma_radps": imu.gyro_bias_sigma_radps,
                 "yaw_rate_bias_walk_radps_rsqrt_s": imu.gyro_bias_walk_radps_rsqrt_s}
    # the gyro's angle random walk plus its bias taken as white over ISAM2_BIAS_HORIZON_S: with the
    # yard default (0.002 rad/sqrt(s), 20x this) iSAM2 took its heading from the landmarks
    # (-1.8 deg over the first 400 m of rocky-1km; docs/smoother.md, "Long traverses")
    rot = math.sqrt(imu.gyro_noise_radps_rsqrt_hz ** 2 + ISAM2_BIAS_HORIZON_S * imu.gyro_bias_sigma_radps ** 2)
    isam2: dict = {"odometry": {"sigma_rot_radpsqrts": float(f"{rot:.4g}")}}
    if not (st.extrinsic_sigma_deg or st.depth_scale_sigma or st.centre_error_frac):
        return {"ekf": ekf, "isam2": isam2}
    if st.centre_error_frac:
        ekf["rock_cov_scale"] = 4.0
        # the smoother's association (not its factors): a per-rock centre error does not average
        # out over frames, as the landmark store's fused covariance assumes (docs/smoother.md,
        # "The association's rock error")
        isam2["landmarks"] = {"association_cov_scale": 1.5}
    cal_e: dict = {}
    cal_i: dict = {}
    if st.extrinsic_sigma_deg:
        cal_e.update(roll_pitch_sigma_deg=st.extrinsic_sigma_deg, yaw_sigma_deg=st.extrinsic_sigma_deg)
        # the smoother estimates the mounting's roll and pitch but not its yaw: with the yaw as a
        # variable its heading ran off where rocks are few (plains-2km +3.9 deg in 3000 s against
        # the IMU's +0.4); without the pitch the landmarks pulled its height off at the pitch's
        # slope (plains-2km with fixes: 8.5 m after 2 km; with it 0.58 m)
        cal_i["roll_pitch_sigma_deg"] = st.extrinsic_sigma_deg
    if st.depth_scale_sigma:
        cal_e["scale_sigma"] = cal_i["scale_sigma"] = st.depth_scale_sigma
    if cal_e:
        ekf["calibration"] = cal_e
    if cal_i:
        isam2["calibration"] = cal_i
    if cfg.world in TILED_PRESETS and TILED_PRESETS[cfg.world].sparse_ground:
        sparse_ground_model(isam2, imu)
    return {"ekf": ekf, "isam2": isam2}


# the wheels' slip as the smoother's variable: the EKF's slip state's sigma (ekf.config.EkfConfig)
SPARSE_GROUND_SLIP_SIGMA = 0.05


def sparse_ground_model(isam2: dict, imu) -> None:
    """The smoother's model where landmarks are few (``isam2`` overrides, changed in place): the
    gyro's yaw-rate bias and the wheels' slip as variables, as the EKF has them (the rotation noise
    the gyro's own angle random walk, its bias no longer folded in), and the mounting's roll held
    at its nominal (a roll of the camera, 20 deg down, turns the base's heading where no landmark
    holds it). On sparse-5km, iSAM2 + reloc against the kilometre model (docs/smoother.md): seed 0
    2.5 km 0.967 -> 0.858 m, seed 1 1.5 km 9.543 -> 3.829 m, seed 2 1.5 km 0.943 -> 0.563 m; on
    rocky-1km and cratered-3km (500 m, seed 0) it cost 9 % and 30 %, so the dense presets keep
    the kilometre model. Without fixes it drifts more (sparse-5km seed 0 2.5 km 33-36 m against
    20.0 m, seed 2 1.5 km 15.8 m against 6.6 m; either variable alone drifts as the kilometre
    model, the two together do not, not traced): it is taken for relocalizing."""
    odo = isam2.setdefault("odometry", {})
    odo.update(sigma_rot_radpsqrts=float(imu.gyro_noise_radps_rsqrt_hz),
               yaw_rate_bias_sigma_radps=float(imu.gyro_bias_sigma_radps),
               yaw_rate_bias_walk_radps_rsqrt_s=float(imu.gyro_bias_walk_radps_rsqrt_s),
               slip_sigma=SPARSE_GROUND_SLIP_SIGMA)
    if "calibration" in isam2:
        isam2["calibration"]["roll_sigma_deg"] = 0.0

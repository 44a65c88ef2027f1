"""Frozen configuration of a simulator run: world, traverse, rover and sensors, defaults in code.

``SimConfig(world="my2021", seed=0)`` is a complete configuration. Fields left at ``None`` take the
world preset's value (traverse length and duration, rock count) or the orbital preset's value; the
run stores the resolved config (``SimRun.config``), in which every ``None`` has been filled in, so
the saved ``world.yaml`` reproduces the run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from sim.errors import SimError
from sim.faults import FaultsConfig, validate_faults
from sim.tiled.config import TiledWorldConfig


class SimConfigError(SimError, ValueError):
    """A simulator configuration value is invalid."""


@dataclass(frozen=True)
class WorldGenConfig:
    """Procedural world: heightmap grid and rock field (sizes follow a power law)."""

    resolution_m: float = 0.15  # heightmap grid spacing
    n_rocks: int | None = None  # None: the preset's rock count
    rock_min_diameter_m: float = 0.10
    rock_max_diameter_m: float = 1.50
    rock_cumulative_exponent: float = 2.0  # N(>D) ~ D^-alpha: many small rocks, few large
    rock_embed_fraction: float = 0.15  # fraction of a rock's height below the ground
    rock_icosphere_subdivisions: int = 1  # 80 triangles per rock


@dataclass(frozen=True)
class TraverseConfig:
    """Route and timing. ``distance_m`` None: preset length; ``duration_s`` None: distance / preset mean speed."""

    distance_m: float | None = None
    duration_s: float | None = None
    edge_margin_m: float = 4.0  # waypoints stay this far inside the world
    segment_min_m: float = 5.0
    segment_max_m: float = 12.0
    heading_sigma_deg: float = 55.0  # spread of heading change between route segments
    avoid_rock_diameter_m: float = 0.5  # the route keeps clear of rocks at least this big
    rock_clearance_m: float = 0.5
    start_pause_s: float = 2.0  # the rover stands still before it drives


@dataclass(frozen=True)
class RoverConfig:
    """JPL Open Source Rover kinematics and the pure-pursuit waypoint controller."""

    wheelbase_m: float = 0.52  # front-to-rear corner wheel distance
    track_m: float = 0.46  # left-to-right wheel distance
    base_height_m: float = 0.15  # base_link above the wheel contact plane
    cruise_speed_mps: float | None = None  # None: 1.25 x the preset mean speed
    max_speed_mps: float = 0.30
    accel_mps2: float = 0.10
    max_yaw_rate_radps: float = 0.35
    turn_yaw_rate_radps: float = 0.25  # turning in place
    yaw_accel_radps2: float = 0.5
    lookahead_m: float = 1.2
    turn_in_place_deg: float = 50.0  # heading error above which the rover stops and turns
    turn_done_deg: float = 4.0


@dataclass(frozen=True)
class CmdConfig:
    """Commanded velocity at ``rate_hz`` and the wheel slip between command and true motion.

    True forward speed = command / (1 + k * s(t)), s(t) = slip_mean + Ornstein-Uhlenbeck(sigma, tau)
    + slope gain * uphill pitch. With ``target_drift_pct`` set, the slip amplitude k is solved per run
    so that command-only dead reckoning (command speed + IMU orientation) ends that far off, in
    percent of the distance; None keeps k = 1.
    """

    rate_hz: float = 30.0
    slip_mean: float = 0.03
    slip_ou_sigma: float = 0.02
    slip_ou_tau_s: float = 20.0
    slip_slope_gain: float = 0.5  # extra slip per radian of uphill pitch (downhill: less)
    yaw_scale_sigma: float = 0.03  # true yaw rate = cmd * (1 + scale) + OU error
    yaw_ou_sigma_radps: float = 0.004
    yaw_ou_tau_s: float = 10.0
    target_drift_pct: float | None = 2.0
    slip_gain_bounds: tuple[float, float] = (0.05, 6.0)


@dataclass(frozen=True)
class ImuConfig:
    """30 Hz IMU: gyro bias + white noise integrated into a drifting yaw; roll/pitch from gravity."""

    rate_hz: float = 30.0
    gyro_bias_sigma_radps: float = 1.0e-5  # constant bias per axis (about 2 deg/h)
    gyro_bias_walk_radps_rsqrt_s: float = 2.0e-7
    gyro_noise_radps_rsqrt_hz: float = 4.4e-5  # angular random walk about 0.15 deg/sqrt(h)
    attitude_noise_rad: float = 0.002  # roll/pitch error of the gravity-referenced attitude
    accel_bias_sigma_mps2: float = 0.02
    accel_noise_mps2_rsqrt_hz: float = 0.003
    gravity_mps2: float = 9.81


@dataclass(frozen=True)
class StereoConfig:
    """Stereo rock detector on the mast camera; defaults reproduce the published rover detector."""

    rate_hz: float = 2.0
    width_px: int = 2304
    height_px: int = 1296
    hfov_deg: float = 80.0
    baseline_m: float = 0.12
    mount_xyz_m: tuple[float, float, float] = (0.15, 0.0, 0.85)  # camera centre in base_link
    mount_tilt_deg: float = 20.0  # pitch down of the optical axis
    min_range_m: float = 0.6
    max_range_m: float = 10.0
    rays_per_rock: int = 7
    min_visible_fraction: float = 0.4  # share of a rock's sample rays that must hit it first
    sigma_disparity_px: float = 0.3  # sigma_z = z^2 * sigma_disp / (f * baseline)
    sigma_pixel_px: float = 2.0  # centroid error across the line of sight
    size_sigma_rel: float = 0.15
    recall: float = 0.692  # detected true / visible true rocks
    precision: float = 0.744  # true / all detections
    detect_log_slope: float = 3.0  # logistic slope of detection probability in log(apparent px)
    fp_size_m: tuple[float, float] = (0.08, 0.4)
    score_true: tuple[float, float] = (7.0, 3.0)  # Beta(a, b) of true detection scores
    score_false: tuple[float, float] = (3.0, 3.0)
    # Systematic errors (fixed per rock or per run, not white). Stereo sees a rock's front surface
    # and the pipeline moves it back along the line of sight by a fixed share of the rock's size
    # (reloc.stereo: 0.3 diameters); real rocks differ in shape, so each rock's centre estimate is
    # off along the line of sight by a per-rock normal draw of centre_error_frac x its radius,
    # which the detector reports as that line-of-sight sigma. The mast camera's mounting is
    # known only to extrinsic_sigma_deg per axis and its depth scale (baseline calibration) to
    # depth_scale_sigma; these two are unreported.
    centre_error_frac: float = 0.0
    extrinsic_sigma_deg: float = 0.0
    depth_scale_sigma: float = 0.0


@dataclass(frozen=True)
class CraterSensorConfig:
    """Crater rims seen by the mast stereo (kilometre worlds; :mod:`sim.sensors.craters`)."""

    enabled: bool = True
    min_diameter_m: float = 1.0  # smaller rims are lost in the rocks and the ripples
    min_range_m: float = 1.0
    max_range_m: float = 25.0  # rim points beyond this are not fitted (stereo depth sigma ~1 m there)
    min_completeness: float = 0.15  # share of the rim in view (54 deg of arc) for a crater to be recognised
    min_apparent_deg: float = 5.0  # the rim spans at least this angle from the camera (1 m: 11 m away)
    n_rim_samples: int = 72  # rim samples that decide what is in view
    rim_points_per_m: float = 2.0  # independent stereo rim points per metre of rim in view
    max_rim_points: int = 200
    irregularity_frac: float = 0.02  # rim departs from a circle by this x D (1 sigma, per point)
    centre_bias_frac: float = 0.01  # per-crater fixed centre offset sigma / D (rim shape)
    rim_height_sigma_frac: float = 0.01  # per-crater fixed offset of the rim centre's height / D
    recall_fresh: float = 0.9  # detection probability of a fresh crater in view
    degradation_penalty: float = 0.5  # ... times (1 - penalty x degradation)
    rate_hz: float = 0.5  # crater frames per second (rims change slowly with the view)


@dataclass(frozen=True)
class OrbitalConfig:
    """Nadir rock detector that makes the catalog. ``preset`` 'published' or 'ideal'; None fields
    take the preset's value (see :data:`ORBITAL_PRESETS`)."""

    preset: str = "published"
    gsd_m: float = 0.05
    sigma_position_px: float | None = None
    size_sigma_rel: float | None = None
    recall: float | None = None  # detected true / all true rocks
    precision: float | None = None  # true / all catalog entries
    min_size_px: float | None = None  # smaller rocks are never detected
    detect_size_width_rel: float = 0.35  # softness of the size threshold of detection
    # what ``recall`` counts: "all" true rocks (the yards) or the "detectable" ones (>= min_size_px)
    recall_basis: str = "all"


ORBITAL_PRESETS: dict[str, dict[str, float]] = {
    "published": {"sigma_position_px": 2.0, "size_sigma_rel": 0.2, "recall": 0.364, "precision": 0.44, "min_size_px": 2.0},
    "ideal": {"sigma_position_px": 0.2, "size_sigma_rel": 0.02, "recall": 1.0, "precision": 1.0, "min_size_px": 3.0},
}


@dataclass(frozen=True)
class SensorsConfig:
    cmd: CmdConfig = field(default_factory=CmdConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    orbital: OrbitalConfig = field(default_factory=OrbitalConfig)
    craters: CraterSensorConfig = field(default_factory=CraterSensorConfig)
    wheel_odometry: bool = True
    wheel_speed_noise_rel: float = 0.005


@dataclass(frozen=True)
class SimConfig:
    """A whole simulator run. ``world``: a yard preset name (my2020, my2021, my2022, cnes), a
    kilometre preset (plains-2km, rocky-1km, cratered-3km, sparse-5km: build its config with
    :func:`sim.tiled.preset_config`) or a Gazebo model directory holding ``model.sdf``."""

    world: str = "my2021"
    seed: int = 0
    worldgen: WorldGenConfig = field(default_factory=WorldGenConfig)
    traverse: TraverseConfig = field(default_factory=TraverseConfig)
    rover: RoverConfig = field(default_factory=RoverConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    t_start_s: float = 0.0
    tiled: TiledWorldConfig = field(default_factory=TiledWorldConfig)  # the kilometre presets' world
    faults: FaultsConfig = field(default_factory=FaultsConfig)  # sensor faults (sim/faults.py), all off


def resolve_orbital(cfg: OrbitalConfig) -> OrbitalConfig:
    """Fill the ``None`` fields of ``cfg`` from its preset."""
    if cfg.preset not in ORBITAL_PRESETS:
        raise SimConfigError(f"sensors.orbital.preset must be one of {sorted(ORBITAL_PRESETS)}, got {cfg.preset!r}")
    fill = {k: v for k, v in ORBITAL_PRESETS[cfg.preset].items() if getattr(cfg, k) is None}
    out = dataclasses.replace(cfg, **fill)
    if out.recall_basis not in ("all", "detectable"):
        raise SimConfigError(f"sensors.orbital.recall_basis must be 'all' or 'detectable', got {out.recall_basis!r}")
    if not (0.0 < out.recall <= 1.0 and 0.0 < out.precision <= 1.0):
        raise SimConfigError(f"orbital recall/precision must be in (0, 1], got {out.recall}, {out.precision}")
    return out


def validate(cfg: SimConfig) -> None:
    """Raise :class:`SimConfigError` naming the first out-of-range value."""
    st = cfg.sensors.stereo
    checks = [
        (cfg.traverse.distance_m is None or cfg.traverse.distance_m > 0, "traverse.distance_m must be > 0"),
        (cfg.traverse.duration_s is None or cfg.traverse.duration_s > 0, "traverse.duration_s must be > 0"),
        (0.0 < st.recall <= 1.0, "sensors.stereo.recall must be in (0, 1]"),
        (0.0 < st.precision <= 1.0, "sensors.stereo.precision must be in (0, 1]"),
        (st.rate_hz > 0 and cfg.sensors.imu.rate_hz > 0, "sensor rates must be > 0"),
        (cfg.sensors.imu.rate_hz == cfg.sensors.cmd.rate_hz, "sensors.cmd.rate_hz must equal sensors.imu.rate_hz"),
        (0.0 < st.hfov_deg < 170.0, "sensors.stereo.hfov_deg must be in (0, 170)"),
        (st.max_range_m > st.min_range_m > 0, "sensors.stereo needs 0 < min_range_m < max_range_m"),
        (cfg.worldgen.resolution_m > 0, "worldgen.resolution_m must be > 0"),
        (0 < cfg.worldgen.rock_min_diameter_m < cfg.worldgen.rock_max_diameter_m, "worldgen rock diameters"),
        (cfg.sensors.craters.max_range_m > cfg.sensors.craters.min_range_m > 0,
         "sensors.craters needs 0 < min_range_m < max_range_m"),
        (0.0 < cfg.sensors.craters.min_completeness <= 1.0, "sensors.craters.min_completeness must be in (0, 1]"),
        (0.0 <= cfg.sensors.craters.recall_fresh <= 1.0 and 0.0 <= cfg.sensors.craters.degradation_penalty <= 1.0,
         "sensors.craters.recall_fresh and degradation_penalty must be in [0, 1]"),
        (cfg.sensors.craters.rate_hz > 0 and cfg.sensors.craters.n_rim_samples >= 8
         and cfg.sensors.craters.rim_points_per_m > 0 and cfg.sensors.craters.max_rim_points >= 3
         and cfg.sensors.craters.min_diameter_m > 0,
         "sensors.craters needs rate_hz > 0, n_rim_samples >= 8, rim_points_per_m > 0, max_rim_points >= 3, min_diameter_m > 0"),
        (min(cfg.sensors.craters.irregularity_frac, cfg.sensors.craters.centre_bias_frac,
             cfg.sensors.craters.rim_height_sigma_frac) >= 0, "sensors.craters error fractions must be >= 0"),
    ]
    for ok, msg in checks:
        if not ok:
            raise SimConfigError(f"invalid simulator config: {msg}")
    from sim.tiled.presets import is_tiled

    rates = [cfg.sensors.imu.rate_hz, cfg.sensors.cmd.rate_hz, st.rate_hz]
    validate_faults(cfg.faults, max(rates), is_tiled(cfg.world))

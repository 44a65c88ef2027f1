"""Configuration of the EKF-SLAM baseline: one frozen dataclass per stage, defaults in code.

Process-noise model (see :mod:`ekf.motion`): per step of ``dt`` seconds the body-frame
translation and rotation errors are white with variance ``sigma**2 * dt``, where each ``sigma``
(per square-root second) grows linearly with the speed ``|v|`` (m/s), the turn rate ``|w_z|``
(rad/s) and the roughness ``rho = sqrt(w_x**2 + w_y**2)`` (rad/s, roll/pitch rate from the IMU);
plus, for slip, a forward and lateral variance proportional to the distance driven ``|v| dt``
(as in the smoother's odometry model).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from reloc.association import AssociationConfig
from reloc.backend import major_sigma
from reloc.budget import ObservationBudget
from reloc.calibration import CalibrationConfig
from reloc.config import Interval, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from reloc.landmark_book import LandmarkBookConfig


@dataclass(frozen=True)
@checked()
class MotionNoiseConfig:
    """Dynamic process noise. Translation sigmas in m/sqrt(s), rotation sigmas in rad/sqrt(s)."""

    # slip: sigma = this * sqrt(distance driven), m/sqrt(m). Slip is a wheel-soil bias correlated
    # over metres to the whole traverse, so a per-time sigma alone makes a slow rover far too
    # confident (my2022, 0.08 m/s: inside 3 sigma 71 %, NEES 11.9; with these 100 %, NEES 1.2)
    fwd_per_sqrtm: NonNegative = 0.03
    lat_per_sqrtm: NonNegative = 0.015  # lateral (vertical: the per-speed terms; z follows the terrain)
    # slip grows with the slope: the forward sigma per sqrt(m) grows by this per rad of pitch
    # (added in quadrature), as in the smoother's odometry model
    fwd_per_sqrtm_per_rad: NonNegative = 1.5
    fwd_floor: NonNegative = 0.001  # forward (base_link x) noise at rest
    fwd_per_speed: NonNegative = 0.03  # ... per m/s of speed (slip, speed error)
    lat_floor: NonNegative = 0.001  # lateral (y) noise at rest
    lat_per_speed: NonNegative = 0.015  # ... per m/s of speed (side slip)
    lat_per_turn: NonNegative = 0.015  # ... per rad/s of turn rate (skid while turning)
    vert_floor: NonNegative = 0.001  # vertical (z) noise at rest
    vert_per_speed: NonNegative = 0.015  # ... per m/s of speed (terrain following)
    trans_per_rough: NonNegative = 0.025  # added to all three per (m/s speed x rad/s roughness)
    rot_floor: NonNegative = 0.00075  # attitude noise at rest (gyro angle random walk)
    rot_per_turn: NonNegative = 0.005  # ... per rad/s of turn rate (scale-factor error)
    rot_per_rough: NonNegative = 0.005  # ... per rad/s of roll/pitch rate


@dataclass(frozen=True)
@checked()
class FixGateConfig:
    """Gates of the planar global fix (the reference design's distance/yaw gate + Mahalanobis)."""

    # |fix xy - estimate xy at t_meas| above max(distance_m, distance_sigmas x the innovation's
    # largest planar sigma) -> rejected. The metres are the reference design's gate against a
    # confidently wrong match; the sigmas let a filter that has drifted further than that (and
    # knows it) take the fixes it needs (sparse-5km seed 1: a filter 6 m off, its right fixes
    # 6.1-6.3 m away refused by a 3 m gate). 0 sigmas: the metres alone. The Mahalanobis gate
    # below still decides on the whole innovation.
    distance_m: Positive = 3.0
    distance_sigmas: NonNegative = 4.0
    yaw_deg: Annotated[float, Interval(gt=0, le=180)] = 15.0  # |fix yaw - estimate yaw| above this -> rejected
    chi2: Positive = 16.27  # squared Mahalanobis distance (3 dof, 99.9 %) above this -> rejected
    # a fix's height (fgslam.terrain_height): its squared Mahalanobis distance (1 dof, 99.9 %) above
    # this -> the fix is applied without it (the planar part gated as above)
    height_chi2: Positive = 10.83
    # Fixes come from matching a map against one catalog, so their errors are correlated in
    # time. The fix source models that for both back-ends alike (RelocalizerConfig.correlation
    # scales each fix's covariance); this is a second, EKF-only model on top of it: a fix's
    # covariance multiplied by (1 + number of fixes applied with t_meas within this many seconds
    # before it). 0 (default) disables it: counted twice, the EKF + reloc was pessimistic (first
    # 800 m of cratered-3km: position NEES 0.55, ATE 0.175 m; without: 1.11, 0.156 m; docs/ekf.md).
    correlation_s: NonNegative = 0.0
    # How the filter takes the fixes' correlation (docs/ekf.md, "Correlated fixes"). "producer":
    # each fix's covariance as it came (RelocalizerConfig.correlation, "rocks" by default: 1 + the
    # earlier uses of its catalog landmarks, never forgotten). "distance": its match covariance
    # re-scaled (GlobalFix.recorrelated) by reloc.covariance.distance_correlation_scale of the
    # distance from the last fix applied from the same source. "bias": the shared error as a
    # state: per source in bias_sources, a (x, y, yaw) offset of the catalog's fixes, first-order
    # Gauss-Markov along the distance between that source's fixes (correlation length
    # correlation_length_m), stationary covariance bias_share x the fix's match covariance; the
    # rest of it and the rover-relative part are the fix's white noise (correlation_s does not
    # apply to it). A fix from another source is taken as it came. "bias" is the default since
    # 2026-12-07 (lower ATE on the three kilometre worlds' first 500 m and on three yards of four,
    # position NEES nearer 2; my2021 0.026 -> 0.039 m: docs/ekf.md).
    correlation_model: Literal["producer", "distance", "bias"] = "bias"
    correlation_length_m: Positive = 15.0  # the fixes' error correlation measured on rocky-1km (docs/app.md)
    bias_sources: tuple[str, ...] = ("rocks", "craters")
    bias_share: Annotated[float, Interval(gt=0, lt=1)] = 0.9
    # A fix of landmarks identified one by one with catalog entries (GlobalFix.anchors): the
    # entries put on the landmarks' (x, y) instead of a pose update, so an entry's error is counted
    # once however many fixes repeat it (a landmark that left the state: the fix as a pose). Its
    # gate: squared Mahalanobis distance above anchor_chi2_per_dof x its dof -> rejected (2 dof,
    # 6.91: 99.9 %; 4 dof, 4.62 per dof is 99.9 %, so a pair's gate is a little looser).
    anchors: bool = True
    anchor_chi2_per_dof: Positive = 6.91
    # Recovery of an overconfident filter: when the Mahalanobis gate has rejected consensus_n
    # fixes within consensus_window_s whose innovations agree (every xy innovation within
    # consensus_tol_m of their mean, yaw within consensus_tol_deg), the filter, not the fixes, is
    # wrong: the pose covariance is inflated by the innovation and the fix applied. 0 disables.
    consensus_n: NonNegativeInt = 3
    consensus_window_s: Positive = 30.0
    consensus_tol_m: Positive = 0.3
    consensus_tol_deg: Positive = 2.0
    # With the fix's source offset a state (correlation_model "bias"), what a consensus opens. The
    # rejected fixes agree with each other either because the pose is wrong (an unmodelled slip
    # burst) or because they share an error larger than modelled (a match whose covariance is
    # short in one place: on my2021 at 116-142 s, yaw 54 mrad off against a 12 mrad sigma, 16
    # rocks); the filter cannot tell which, so by default both the pose and the source's offset
    # ("pose_and_offset": the landmarks and the next fixes on other catalog entries decide);
    # "pose" or "offset" alone (docs/ekf.md, "Correlated fixes"). Without an offset state, the pose.
    consensus_opens: Literal["pose", "offset", "pose_and_offset"] = "pose_and_offset"

    def distance_limit_m(self, S_xy) -> float:
        """The distance gate for a planar innovation of covariance ``S_xy`` (2, 2):
        ``max(distance_m, distance_sigmas * sqrt(largest eigenvalue))``."""
        if self.distance_sigmas == 0.0:
            return float(self.distance_m)
        return max(float(self.distance_m), self.distance_sigmas * major_sigma(S_xy))


@dataclass(frozen=True)
@checked()
class EkfConfig:
    """Everything the filter needs; see docs/ekf.md for the model."""

    motion: MotionNoiseConfig = field(default_factory=MotionNoiseConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    book: LandmarkBookConfig = field(default_factory=LandmarkBookConfig)
    fix_gate: FixGateConfig = field(default_factory=FixGateConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    # per rock frame: at most max_observations associated observations in the update (confirmed
    # landmarks first, then the lowest innovation covariance) and max_new initialisations
    # (nearest first); see reloc.budget and docs/ekf.md
    budget: ObservationBudget = field(
        default_factory=lambda: ObservationBudget(max_observations=25, max_new=0))
    # A frame whose only association stands beside an ambiguous detection (one that gated to a
    # landmark but was not assigned) is not used for the update: a lone pair has no joint-
    # compatibility check, and an ambiguous scene is where a wrong pair hides (my2022: one such
    # pair after a steep slope moved the rover 0.26 m the wrong way, EKF ATE 0.377 m -> 0.028 m)
    skip_lone_ambiguous_pair: bool = True
    rock_cov_scale: Positive = 1.0  # the detector's reported rock covariance is multiplied by this
    attitude_sigma_rad: Positive = 0.01  # roll/pitch pseudo-measurement from the IMU's gravity reference
    attitude_period_s: float = 1.0  # how often it is applied; <= 0 disables it
    landmark_period_s: NonNegative = 0.2  # rock frames closer than this to the last used one are skipped
    candidate_margin_m: NonNegative = 1.0  # landmarks predicted within max_range + margin are candidates
    # bound on the state; beyond it the stalest landmarks are marginalised. Each update costs
    # ~N^2 (N = 6 + 3 x landmarks). On the dense my2020 yard (seed 0, no fixes) 300 -> 150 took the
    # pass from 28 s to 11 s and the ATE from 0.057 to 0.008 m (100: 0.031, 200: 0.042); my2021,
    # my2022 and cnes kept their ATE (0.018 / 0.028 / 0.030 m)
    max_landmarks: PositiveInt = 150
    # a landmark seen within this many seconds is not marginalised to make room for a new one.
    # 0 (evict by age alone): where more landmarks are in view than the bound holds, a landmark a
    # frame missed is swapped for one it saw, so the state follows the nearest, best-measured
    # rocks (the dense my2020 yard: 0.027 m against 0.048 with 2 s); long traverses get 2 s
    # (fgslam.long_traverse: rocky-1km's rocks were swapped 80 times a second)
    keep_seen_s: NonNegative = 0.0
    # landmarks farther than this (m, planar) from the rover are out of reach and marginalised, so
    # a sparse world's state holds only what the camera can see again; 0 keeps them until the
    # bound above needs the room (long traverses get 40 m, fgslam.long_traverse)
    forget_distance_m: NonNegative = 0.0
    history_s: Positive = 30.0  # late fixes older than this (vs the newest input) are rejected
    checkpoint_period_s: Positive = 2.0  # state snapshots for roll-back (each a copy of P), this far apart
    future_tolerance_s: NonNegative = 0.1  # a fix up to this far ahead of the filter is applied now
    trajectory_period_s: NonNegative = 0.0  # pose history sampling; 0 -> every step
    # First-estimate Jacobians (Huang, Mourikis, Roumeliotis 2008): the Jacobians that couple
    # rotation to position use the pose's propagated position and each landmark's first
    # estimate, so landmarks alone give no information on the yaw and position that SLAM cannot
    # observe. With the current estimate (False) the filter's yaw sigma stayed at 0.2 deg for 3000 s
    # of plains-2km (no fixes) while its yaw error grew to 0.8 deg (docs/ekf.md, "Consistency")
    first_estimate_jacobians: bool = True
    # The IMU's heading drifts at its gyro bias (roll and pitch it corrects from gravity itself),
    # a constant rate that white rotation noise cannot represent: over 3000 s of plains-2km the
    # IMU's heading was 0.48 deg off. With a sigma > 0 the filter estimates that rate as a state
    # (rad/s about world z, this prior sigma, a random walk of bias_walk per sqrt(s)); the
    # landmarks' relative rotations observe it. Defaults: a rover IMU of ~2 deg/h (the
    # simulator's default IMU); `fgslam sim` writes its IMU's figures into backend.yaml; 0: no state
    yaw_rate_bias_sigma_radps: NonNegative = 1.0e-5
    yaw_rate_bias_walk_radps_rsqrt_s: NonNegative = 2.0e-7
    # The wheels lose a share of the commanded distance to the soil (a few per cent on loose
    # ground, varying with the terrain): a bias that the white slip terms of MotionNoiseConfig
    # (0.3 % of 100 m at 0.03 m/sqrt(m)) cannot represent. With a sigma > 0 the filter estimates it
    # as a state (v_true = (1 - slip) v; this prior sigma around 0, a random walk per sqrt(s)); the
    # landmarks' motion against the wheels' observes it, so the stereo range scale is no longer
    # pulled by the wheels' bias (plains-2km, 3000 s, no fixes: scale 0.982 -> 0.999 against the
    # true 0.997, ATE 2.02 -> 0.88 m, position NEES 12.7 -> 1.40; docs/ekf.md). 0: no state
    slip_sigma: NonNegative = 0.05
    slip_walk_rsqrt_s: NonNegative = 5.0e-4
    # Slip grows with the slope: wheels on loose soil lose more of the commanded distance uphill
    # and less downhill (terramechanics; a rover's slip-vs-slope curve). With a sigma > 0 (and the
    # slip state on) the filter estimates the gain as a state, slip = g + gain * (uphill pitch,
    # rad), instead of carrying a slip learned on one slope onto the next (my2020 seed 1, 2
    # minutes blind: slip learned at 0.066 on the flat, true -0.03 to -0.05 on the 3-5 deg
    # downhill that followed, the estimate 0.52 m behind along-track in 6 m at a 0.26 m sigma;
    # with the gain 0.39 m at 0.39 m). Prior around 0, this sigma per rad; a random walk per
    # sqrt(s) lets it follow the soil. Off (0) by default: the yards' gentle pitch teaches it
    # little (1.0 -> 0.5-0.7 in a minute) and a wrong gain drives the next slope wrong (fault
    # bench, 3 seeds, blackout and no-rocks: summed ATE 1.89 -> 2.10 m; docs/ekf.md)
    slope_slip_sigma_per_rad: NonNegative = 0.0
    slope_slip_walk_rsqrt_s: NonNegative = 1.0e-3
    # Around that bias the slip wanders with the soil under the wheels: a first-order Gauss-Markov
    # term o (d o = -o dt / tau + w, stationary sigma slip_gm_sigma, as the simulator's wheels:
    # sim.config.CmdConfig 0.02 over 20 s times its slip gain ~1.5) that the bias's slow random
    # walk cannot follow: through a blind stretch the error grows like sigma x distance. On a
    # synthetic drive with that wander the filter without the state ends 40 s blind optimistic
    # (ANEES 6.1 over 4 seeds), with it inside the interval (2.8; tests/ekf/test_slip_state.py).
    # Off (0) by default: on the simulator's yards and kilometre worlds the white slip terms of
    # MotionNoiseConfig already cover it, and the state did not pay (docs/ekf.md: fault bench
    # blind ATE 1.89 -> 1.41-1.86 m summed but pessimistic or unchanged, rocky-1km 400 m with
    # fixes 0.126 -> 0.166 m, plains 3000 s 0.556 -> 0.527 m). Turn it on (0.03) with
    # motion.fwd_per_sqrtm_per_rad 0.75 where the soil changes along the way
    slip_gm_sigma: NonNegative = 0.0
    slip_gm_tau_s: Positive = 20.0
    # when an update moves the pose more than this (m) from its first estimate, every first
    # estimate is replaced by the current one: a first-estimate Jacobian assumes small corrections
    # (after the consensus reset of a filter whose map is 1.5 m off, the landmark updates moved
    # the pose by decimetres per frame, and the filter followed the fixes to 0.37 m instead of
    # 0.14 m). Landmarks are never re-linearised alone: on the synthetic test world that took the
    # yaw sigma from its start's 3 deg to 0.4 deg with no yaw information at all
    first_estimate_tol_m: Positive = 0.1
    blas_threads: NonNegativeInt = 1  # BLAS threads during updates (see ekf.blas); 0 -> library default
    # settings of the other landmark kinds' EKF updates, by kind name (each kind's layer declares
    # its config class; the rock settings are the fields above), see ekf.kinds
    kinds: dict = field(default_factory=dict)

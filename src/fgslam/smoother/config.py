"""Configuration of the iSAM2 smoother: one frozen dataclass per stage, defaults in code.

Noise sigmas carry their unit in the name. ``SmootherConfig`` nests the stage configs so that
``reloc.config.config_from_dict(SmootherConfig, yaml_dict)`` overrides any of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Annotated, Literal

from fgslam.errors import SmootherError
from reloc.association import AssociationConfig
from reloc.budget import ObservationBudget
from reloc.calibration import CalibrationConfig
from reloc.config import Interval, NonNegative, NonNegativeInt, Positive, PositiveInt, checked


class Factorization(str, Enum):
    """Linear solver inside iSAM2. Cholesky is the default: it is ~40 % faster than QR and, with
    the gravity factors anchoring roll and pitch, does not meet the "Indeterminant linear system"
    failure; QR is the fallback the smoother switches to if Cholesky ever fails."""

    CHOLESKY = "cholesky"
    QR = "qr"


@dataclass(frozen=True)
@checked(SmootherError)
class KeyframeConfig:
    """When to start a new keyframe: whichever of distance, heading change or time comes first."""

    distance_m: Positive = 0.5
    yaw_rad: Positive = 0.2
    interval_s: Positive = 1.0


@dataclass(frozen=True)
@checked(SmootherError)
class OdometryNoiseConfig:
    """Per-step odometry noise (command speed held over an IMU step, IMU orientation increment).

    Translation variance grows linearly with the distance driven (slip is correlated over
    metres, so per-step noise proportional to the step would be far too optimistic), rotation
    variance with time (gyro random walk); the floors keep a stationary rover's between-factor
    well conditioned.
    """

    # forward slip: sigma = this * sqrt(distance). Slip is correlated far beyond a keyframe (a
    # wheel-soil bias), which a white model can only cover by a larger sigma: with 0.04 / 0.02
    # iSAM2 + reloc on my2022 was inside 3 sigma 55 % of the time (ATE 0.096 m), with 0.08 / 0.04
    # 100 % (0.041 m)
    sigma_forward_m_per_sqrtm: Positive = 0.08
    sigma_lateral_m_per_sqrtm: Positive = 0.04  # lateral/vertical
    # slip grows with the slope (wheels on loose soil uphill): forward sigma per sqrt(m) grows by
    # this per rad of pitch (IMU gravity reference), added in quadrature. cnes seed 3 climbs
    # 1.5 m in 60 s: a 0.6 m slip burst over 3 m left iSAM2 + reloc 0.6 m off its own map
    sigma_forward_m_per_sqrtm_per_rad: NonNegative = 1.5
    sigma_rot_radpsqrts: Positive = 0.002  # orientation increment, rad per sqrt(s)
    floor_sigma_m: Positive = 1e-4  # per step
    floor_sigma_rad: Positive = 1e-5  # per step
    gravity_sigma_rad: Positive = 0.01  # roll/pitch from the IMU's gravity reference
    # the wheels' slip as a variable g per keyframe (the odometry's translation is (1 - g) times the
    # commanded one): a bias over hundreds of metres (a wheel-soil property, varying with the
    # terrain) that the white terms above cannot represent, and that would otherwise pull the
    # stereo scale and bias the distance driven where landmarks are sparse. Its prior sigma at the
    # start and its random walk per sqrt(s) between keyframes, as the EKF's slip state
    # (ekf.config.EkfConfig.slip_sigma); 0: no variable (a long traverse takes
    # long_traverse.isam2_slip_sigma, 0.05)
    slip_sigma: NonNegative = 0.0
    slip_walk_rsqrt_s: NonNegative = 5.0e-4
    # the IMU heading's drift rate about world z as a variable per keyframe (rad/s; its prior sigma
    # at the start and its random walk per sqrt(s)), taken out of the odometry's rotation as the
    # EKF's yaw-rate bias state (ekf.config.EkfConfig.yaw_rate_bias_sigma_radps); 0: no variable
    yaw_rate_bias_sigma_radps: NonNegative = 0.0
    yaw_rate_bias_walk_radps_rsqrt_s: NonNegative = 2.0e-7


@dataclass(frozen=True)
@checked(SmootherError)
class LandmarkConfig:
    """Rock landmarks: association, insertion and the robust point factor."""

    # rock frames come at 1 Hz here (min_frame_interval_s): persistence spans the two before, and
    # an uncertain pair (an old landmark after a blind spell) needs both to agree: with one, the
    # fault bench's clutter-only stretch (no_rocks, my2020 seeds 0-2) left iSAM2 optimistic in 6
    # of 6 blind windows (NEES 4.2-27.8); with two in none (0.35-3.46), its sigma growing as in a
    # camera blackout (docs/sim.md)
    association: AssociationConfig = field(
        default_factory=lambda: AssociationConfig(persistence_s=2.5, persistence_n_uncertain=2,
                                                  persistence_any_detection=True))
    min_obs_to_insert: PositiveInt = 2  # observations (on distinct keyframes) before a rock enters the graph
    candidate_timeout_s: Positive = 10.0  # a candidate not confirmed within this is dropped
    huber_k: Positive = 3.0  # on the whitened 3-dof residual
    rock_cov_scale: Positive = 1.0  # the detector's reported rock covariance is multiplied by this
    # the association's model of a rock detection's error: this times the factors' covariance (above).
    # The store fuses a landmark's detections as independent, so its covariance shrinks as 1/n,
    # while an error that persists over frames (a stereo pipeline's per-rock centre error) does
    # not average out: the joint-compatibility test then took the landmarks for better known than
    # the pose and refused whole frames' worth of good pairs (docs/smoother.md, "The
    # association's rock error"). The factors keep the detector's covariance. The crater layer's
    # store takes it too (its settings are these with the crater ones replaced): a crater's rim
    # centre error persists over frames in the same way
    association_cov_scale: Positive = 1.0
    min_range_m: NonNegative = 0.3
    min_frame_interval_s: NonNegative = 0.95  # rock frames closer than this to the last used one are skipped
    # (only one observation per landmark and keyframe enters the graph, so more frames add little:
    # 2 Hz -> 1 Hz halved the association cost and lowered the ATE, 0.028 -> 0.021 m on the simulator)
    # per rock frame: at most max_observations factors of graph landmarks (lowest innovation
    # covariance first; candidates' observations cost nothing and are all kept), and, where
    # dense_view or more graph landmarks are in view (0: everywhere), at most max_new candidates
    # entering the graph (best constrained first, the others wait); see docs/smoother.md
    budget: ObservationBudget = field(
        default_factory=lambda: ObservationBudget(max_observations=25, max_new=3))
    dense_view: NonNegativeInt = 60
    max_retired: NonNegativeInt = 5000  # landmarks kept (frozen) after leaving the fixed-lag window
    # association gates a landmark last seen on an older keyframe with the uncertainty the pose
    # gained since (causal covariances), as the EKF's joint covariance does: after a camera
    # blackout the old landmarks are re-found instead of mapped anew (docs/smoother.md)
    gate_with_cov_growth: bool = True



@dataclass(frozen=True)
@checked(SmootherError)
class FixConfig:
    """Late global (x, y, yaw) fixes: gate, robust kernel, retraction, history."""

    gate_chi2: Positive = 30.0  # Mahalanobis gate on the innovation (3 dof)
    # a fix's height (fgslam.terrain_height): squared Mahalanobis distance (1 dof, 99.9 %) above this
    # -> the fix is placed without it
    height_gate_chi2: Positive = 10.83
    gate_distance_m: Positive = 25.0  # hard gate on the position innovation
    cauchy_k: Positive = 2.0  # Cauchy kernel scale on the whitened residual
    # ... in the innovation's sigmas (the keyframe's causal covariance and the fix's) rather than the
    # fix's alone: a fix inside the gates is not taken for an outlier because the estimate has
    # drifted (k scaled by fixes.kernel_scale; without it a smoother 6 m off, knowing it, retracted
    # every right fix of 0.3 m: tests/fgslam/test_fix_hold.py)
    kernel_on_innovation: bool = True
    # ... only beyond an estimate this many times as uncertain as the fix (in sigma): below it the
    # scale stays cauchy_k in the fix's sigmas, which down-weights a confident fix's own error the
    # most (on sparse-5km seeds 1 and 2 the whole-ratio scale moved the heading by fixes the kernel
    # had tempered, and the drift after them grew: docs/smoother.md); 0: the whole ratio
    kernel_widen_above: NonNegative = 3.0
    retract_chi2: Positive = 16.27  # post-optimisation residual above this -> fix removed (3 dof, 0.999)
    retract_chi2_with_height: Positive = 18.47  # ... for a fix with a height (4 dof, 0.999)
    max_age_s: Positive = 60.0  # odometry history kept to place late fixes
    # A fix of landmarks identified one by one with catalog entries (GlobalFix.anchors): the
    # entries as priors on the landmarks' (x, y) instead of a factor on the pose, so an entry's
    # error is counted once however many fixes repeat it (a landmark not a variable of the
    # solver: the fix as a pose). Gate: squared Mahalanobis distance above anchor_chi2_per_dof x
    # its dof (2 per landmark; 6.91: 99.9 % for one) -> rejected; the distance gate per landmark.
    anchors: bool = True
    anchor_chi2_per_dof: Positive = 6.91
    extra_iterations: NonNegativeInt = 1  # extra iSAM2 updates after a fix (one Gauss-Newton step each)
    window_margin_s: NonNegative = 2.0  # fixed-lag: refuse fixes this close to the window edge
    # With a calibration variable (SmootherConfig.calibration), a fix's yaw sigma is taken as at
    # least this: a fix's heading comes from the map, whose rotation follows the calibration's yaw,
    # so the two would feed each other (realistic errors, my2020: yaw calibration -0.55 deg against
    # the drawn -0.05, ATE 0.148 m, inside 3 sigma 24 %; with 0.05: -0.047 deg, 0.031 m, 100 %)
    calibrated_yaw_sigma_floor_rad: NonNegative = 0.05
    # How the smoother takes the error its pose fixes share (successive fixes from one catalog
    # match the same entries): "producer", each fix's covariance as it came
    # (RelocalizerConfig.correlation's factor counts n fixes on shared entries as about ln n
    # independent ones); "bias", the shared error as variables, the EKF's model
    # (ekf.config.FixGateConfig.correlation_model): per source in bias_sources, a (x, y, yaw)
    # offset O(j) of the catalog's fixes, one per applied fix, first-order Gauss-Markov along the
    # distance between that source's fixes (correlation length correlation_length_m, times the
    # share of the fix's catalog entries that the source's last fix used too), stationary
    # covariance bias_share x the fix's match covariance; the rest of it and the rover-relative
    # part are the fix factor's own noise (fgslam.smoother.fix_offsets; docs/smoother.md, "The
    # fixes' shared error as variables"). Anchored fixes count each entry once already. Long
    # traverses take "bias" (long_traverse.isam2_fix_correlation_model: the fixed-lag window keeps
    # the chain of offsets short); with the full history it spans the whole run, and iSAM2 took 4x
    # as long on my2020 for 5 % more error
    correlation_model: Literal["producer", "bias"] = "producer"
    correlation_length_m: Positive = 15.0
    bias_sources: tuple[str, ...] = ("rocks", "craters")
    bias_share: Annotated[float, Interval(gt=0, lt=1)] = 0.9
    gate_smoothed_marginal: bool = False  # gate with the keyframe's smoothed marginal (5-40 ms for a
    # keyframe 30 s old, the path to the Bayes tree root) instead of its causal covariance (an
    # upper bound: the gate is slightly looser, retraction still catches what passes)


@dataclass(frozen=True)
@checked(SmootherError)
class SmootherConfig:
    """All settings of :class:`fgslam.smoother.Isam2Smoother`.

    ``fixed_lag_s`` > 0 switches to the fixed-lag smoother (bounded cost, keys older than the lag
    are marginalized; the calibration variable is re-stamped at every keyframe and stays in the
    window); 0 keeps the full history in one iSAM2. Long traverses get the fixed-lag smoother by
    default (:mod:`fgslam.long_traverse`).
    """

    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    odometry: OdometryNoiseConfig = field(default_factory=OdometryNoiseConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)
    fixes: FixConfig = field(default_factory=FixConfig)
    factorization: Factorization = Factorization.CHOLESKY
    # after Cholesky fails (an indeterminate system) the smoother runs QR for this many updates,
    # doubled at each further failure, then Cholesky again: QR held for good made a cratered-3km
    # run 3-4x slower (73 % of its time in QR elimination) after one failure at keyframe 5103
    cholesky_retry_updates: PositiveInt = 200
    relinearize_threshold: NonNegative = 0.01  # keyframe poses: relinearize when |delta| (rad, m) exceeds this
    landmark_relinearize_scale: Positive = 5.0  # rock landmarks relinearize at this times the pose
    # threshold (m): each relinearized landmark re-eliminates every clique it is in, and ~500 of
    # them moving by a few mm dominated the update cost (x1.4 real time on the 1000 s simulator
    # traverse, same ATE; 20 raised the ATE by 40 %). Full mode only (fixed-lag: the next setting)
    # fixed-lag (long traverses): a pose's translation and a landmark relinearize when they moved
    # more than this (m); rotations keep relinearize_threshold. A fix moves the whole window by
    # decimetres: at 0.01 m every relinearization check relinearized nearly every variable and
    # iSAM2 fell back to a batch step (first 800 s of rocky-1km: 42 of 866 updates, 56 % of the
    # update time, ~460 ms each); at 0.1 m 5 batches, update time 35.9 -> 19.9 s, p99 519 -> 51 ms,
    # ATE 0.074 -> 0.069 m, the same 66 fixes. 0: relinearize_threshold for everything
    fixed_lag_translation_threshold_m: NonNegative = 0.1
    relinearize_skip: PositiveInt = 10  # relinearization check every 10 updates (halved p99 on the simulator)
    partial_relinearization_check: bool = True  # iSAM2 checks for relinearization only from the
    # root down while deltas exceed the threshold (x1.3 real time on the simulator, ATE +2 %)
    fixed_lag_s: NonNegative = 0.0
    # fixed-lag: keys are stamped with their keyframe's time rounded down to a multiple of this,
    # so they leave the window in batches once per period (the window spans fixed_lag_s to
    # fixed_lag_s + this). Every update that marginalizes makes GTSAM's fixed-lag smoother
    # re-order the tree with the leaving keys first: marginalizing at every keyframe re-eliminated
    # about half the window at each update (docs/smoother.md, "Fixed-lag cost"). 0: every keyframe;
    # full mode: unused
    marginalize_every_s: NonNegative = 5.0
    # fixed-lag: GTSAM keeps a slot for every factor ever added (removed and marginalized ones
    # stay as null pointers in its nonlinear and linear graphs): ~26 a keyframe update, 531 000
    # slots for ~4 000 live factors at the end of plains-2km (2 km), growing with the distance.
    # When the slots reach this many (and 2 x the live factors), the solver is rebuilt from its
    # live factors and linearization point (a batch step, as iSAM2 takes on its own); 0: never
    compact_after_slots: NonNegativeInt = 50_000
    frozen_marginals: bool = False  # fixed-lag: marginal covariance of a keyframe as it leaves the
    # window (~1 ms each) instead of its causal covariance (an upper bound)
    # fixed-lag: the newest keyframe's covariance after an update that marginalized keys is its
    # prediction (the previous keyframe's marginal moved by the odometry between them: an upper
    # bound, as the estimate between keyframes) instead of its marginal. GTSAM's fixed-lag
    # smoother re-orders the tree with the leaving keys first and leaves the newest keyframe
    # wherever COLAMD puts it, so its marginal went through a long shortcut: 188 ms of the
    # slowest keyframes' 220 (rocky-1km, window 120 s; docs/smoother.md, "Fixed-lag cost")
    predicted_cov_when_marginalizing: bool = True
    snapshot_before_fixes: bool = True  # full mode: copy ISAM2 (~ms) before fix updates and retractions
    # stereo calibration variable C(0) (rotation error, scale) with this prior, on every rock
    # factor (then a Python factor, ~25 us per linearization instead of the C++ one)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    # how an enabled calibration enters: "estimate", the variable C(0) above; "consider", no
    # variable: the prior's effect on each measurement (J_c Sigma_c J_c^T, J_c = [-[z]x, z]) is
    # added to its covariance and the factors stay C++. Fixed-lag marginalization re-linearizes
    # every factor of the window (GTSAM takes the batch path when most of the tree is re-eliminated),
    # so with C(0) each one cost ~100 ms of Python (rocky-1km, first 600 s, window 120 s: estimate
    # -> consider 43.2 -> 28.3 s, keyframe p99 752 -> 173 ms, ATE 0.242 -> 0.206 m, position NEES
    # 1.92 -> 4.05, slightly optimistic; C(0) had learned yaw 0.15 -> 0.12 deg sigma in 600 s).
    # Long traverses default to "consider" (fgslam.long_traverse). Over longer stretches it is
    # overconfident: the calibration error is shared by every observation, which "consider" takes as
    # independent (plains-2km, first 3000 s, no fixes: NEES 54, ATE 1.26 m; "estimate" 5.9, 2.07 m;
    # docs/app.md)
    calibration_mode: Literal["estimate", "consider"] = "estimate"
    # "consider": the calibration's covariance term is multiplied by this. One calibration error
    # is common to every observation, which the factors take as independent: a rock seen from n
    # keyframes would average it down by n
    calibration_consider_scale: Positive = 1.0
    # settings of the other landmark kinds' smoother layers, by kind name (each layer declares its
    # config class; the rock settings are ``landmarks``), see fgslam.smoother.kinds
    kinds: dict = field(default_factory=dict)

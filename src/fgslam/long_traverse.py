"""Bounded back-ends on long traverses: which settings a stream longer than
``LongTraverseConfig.min_duration_s`` gets by default.

On a yard (10-25 min) the full iSAM2 history is affordable and loop closures are worth keeping;
on a kilometre traverse that never comes back the full graph only grows (cost and memory), so
the smoother runs fixed-lag with a window of ``isam2_fixed_lag_s``, and the EKF marginalises the
landmarks it has left behind (``ekf_forget_distance_m``) instead of holding them until its bound
needs the room, and keeps those still in view (``ekf_keep_seen_s``). The window must be longer
than the worst fix latency, so that no fix is lost to it: a fix is placed on the keyframe at its
``t_meas``, which has to be still inside the window (less its margin) when the fix arrives at
``t_recv``. A fix that is older all the same (a measured matching time far above the configured
delay) is refused with its reason and counted (``n_fixes_older_than_window`` in the smoother's
stats); the smoother stays usable.

An explicit setting in the back-end's overrides always wins (``fixed_lag_s: 0`` keeps the full history).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from fgslam.errors import FgslamError
from fgslam.runner import RunnerConfig
from reloc.backend import Trajectory
from reloc.config import NonNegative, Positive, checked, merged_overrides

KEYFRAME_INTERVAL_S = 1.0  # LongTraverseConfig.isam2_keyframe_interval_s (KeyframeConfig's default)
FRAMES_PER_KEYFRAME = 0.95  # a rock frame per keyframe: min_frame_interval_s this times the interval
PERSISTENCE_FRAMES = 2.5  # the persistence test spans the two frames before: persistence_s this times it


class LongTraverseError(FgslamError):
    """A long-traverse setting that cannot hold (a window shorter than the fix latency)."""


@dataclass(frozen=True)
@checked(LongTraverseError)
class LongTraverseConfig:
    """When a stream is a long traverse, and what its back-ends get then."""

    min_duration_s: Positive = 1800.0  # streams longer than this (s) are long traverses
    isam2_fixed_lag_s: Positive = 120.0  # iSAM2's fixed-lag window (s) on a long traverse
    # iSAM2's stereo calibration on a long traverse (SmootherConfig.calibration_mode): the variable
    # C(0) on every rock factor. "consider" (its prior added to each measurement's covariance, C++
    # factors, ~1.8x faster) averages an error every observation shares: over the first 400 m of
    # rocky-1km its along-track sigma stayed at 5 cm while the error grew to 1 m (position NEES
    # 39). Estimated (the mounting's roll and pitch and the range scale, as the kilometre worlds'
    # backend.yaml sizes them, with the gyro's rotation noise) the position NEES is 0.96-2.46 on
    # the presets' first 400 m (docs/smoother.md)
    isam2_calibration_mode: Literal["estimate", "consider"] = "estimate"
    # iSAM2's keyframe interval on a long traverse (KeyframeConfig.interval_s), with one rock frame
    # per keyframe (LandmarkConfig.min_frame_interval_s, 0.95 of it) and the persistence test
    # spanning the two frames before (AssociationConfig.persistence_s, 2.5 of it), each derived
    # from the keyframe interval the smoother runs with (an explicit keyframes.interval_s in its
    # overrides included) unless set. Each keyframe update re-eliminates the cliques from the
    # landmarks it observes to the root, a path through every keyframe since they were first
    # seen: at 2 s the smoother's time falls ~5x and the ATE with fixes is the same on rocky-1km,
    # plains-2km and cratered-3km, but without fixes it drifts more on 10 of 12 runs (+11 %
    # summed at 500 m) and where fixes are rare (sparse-5km) it loses them, so 1 s stays the
    # default (docs/smoother.md, "Keyframes every 2 s on a long traverse")
    isam2_keyframe_interval_s: Positive = KEYFRAME_INTERVAL_S
    # How iSAM2 takes the error its pose fixes share on a long traverse (FixConfig.correlation_model):
    # "bias", an offset variable per source and fix with a Gauss-Markov step between them
    # (fgslam.smoother.fix_offsets), which the fixed-lag window keeps short. On the first 500 m of
    # rocky-1km, cratered-3km and plains-2km (seeds 0-2), iSAM2 + reloc's ATE lower than with
    # "producer" on 7 of 9 (summed 1.297 -> 1.248 m; cratered-3km seed 1 +25 %), and on the demo's
    # 250 m 0.066 -> 0.056 m, at the same cost; with the full history (a yard) the
    # offset chain spans the whole run and made iSAM2 4x slower on my2020 for 5 % more error, so
    # the smoother's own default stays "producer" (docs/smoother.md, "The fixes' shared error as
    # variables")
    isam2_fix_correlation_model: Literal["producer", "bias"] = "bias"
    # The wheels' slip as iSAM2's variable on a long traverse (SmootherConfig.odometry.slip_sigma,
    # the EKF's slip state's prior; 0: none): a wheel-soil bias over hundreds of metres, which the
    # odometry's white forward noise cannot hold and the stereo scale then absorbs, so that the
    # smoother, without fixes, claimed a distance it did not know. On the first 500 m of rocky-1km,
    # cratered-3km and plains-2km (seeds 0-2): without fixes the ATE lower on 8 of 9 (summed
    # 17.73 -> 13.47 m) and the position ANEES consistent on cratered-3km and plains-2km (4.50 and
    # 5.67, optimistic, -> 2.15 and 3.40), rocky-1km still optimistic (5.86 -> 4.28: a heading the
    # landmarks turn); with fixes summed 1.247 -> 1.183 m (docs/smoother.md, "The slip variable on
    # every long traverse"). The yards keep the smoother's own default, no variable
    isam2_slip_sigma: NonNegative = 0.05
    # the EKF marginalises landmarks this far (m) from the rover: three times the stereo range, a
    # rock that far is behind a rover that does not come back
    ekf_forget_distance_m: Positive = 40.0
    # the EKF keeps a landmark seen within this many seconds rather than swap it for a new one
    # (EkfConfig.keep_seen_s): on rocky-1km's first 1500 s (more rocks in view than its 150
    # slots), with fixes, 0.237 -> 0.187 m ATE (without: 0.629 -> 0.469); on the dense my2020 yard
    # the swap to the nearest rocks is worth more (0.027 m against 0.048 with it)
    ekf_keep_seen_s: NonNegative = 2.0
    # What a long traverse keeps for its evaluation: a pose with its covariance is a 424-B row, so
    # 10 Hz over a 0.12 m/s traverse is ~35 kB per metre for each of the runner's online record
    # and the EKF's pose history: with the ground truth held twice, 0.9 GB over 10 km, the whole
    # growth of `fgslam run`'s memory with distance. The rover moves ~0.1 m a second, its error
    # changes over metres, and iSAM2 keeps one keyframe every isam2_keyframe_interval_s (1 s; its
    # smoothed trajectory has a pose there, the online estimate one a second): one pose a second
    # is the resolution of the estimates. The truth stays at its own rate
    # (held once, fgslam.runner.run_backend's keep_truth), so that evo, which pairs stamps
    # without interpolating, evaluates every pose of ground_truth.tum's run as fgslam does.
    record_rate_hz: Positive = 1.0  # the runner's online estimate at most this often (RunnerConfig.record_rate_hz)
    ekf_trajectory_period_s: Positive = 1.0  # the EKF's pose history (its final trajectory) at most this often


def stream_span_s(measurements) -> float:
    """Span (s) of a measurement stream: a bag source's recorded span, or a list's first to last
    stamp; nan when it cannot be known without reading the stream."""
    span = getattr(measurements, "span_s", None)
    if callable(span):
        t0, t1 = span()
        return float(t1 - t0)
    if isinstance(measurements, (list, tuple)) and measurements:
        return float(measurements[-1].t - measurements[0].t)
    return float("nan")


def run_span_s(truth, measurements, duration_s: float | None = None) -> float:
    """Span (s) a run covers, for the long-traverse decision: ``duration_s`` when the run is cut
    to it, else the ground truth's span, else the stream's (:func:`stream_span_s`)."""
    if duration_s is not None:
        return float(duration_s)
    if truth is not None and len(truth):
        return float(truth.t[-1] - truth.t[0])
    return stream_span_s(measurements)


def is_long(duration_s: float, cfg: LongTraverseConfig) -> bool:
    """Whether a stream of ``duration_s`` is a long traverse (an unknown span is not)."""
    return bool(duration_s > cfg.min_duration_s)


def runner_config_for(runner: RunnerConfig, duration_s: float, cfg: LongTraverseConfig) -> RunnerConfig:
    """The runner's config on a stream of ``duration_s``: on a long traverse the online estimate is
    recorded at most at ``cfg.record_rate_hz`` (a lower rate in ``runner`` stands)."""
    if not is_long(duration_s, cfg) or runner.record_rate_hz <= cfg.record_rate_hz:
        return runner
    return dataclasses.replace(runner, record_rate_hz=cfg.record_rate_hz)


def evaluation_truth(inputs) -> tuple[Trajectory | None, float]:
    """The ground truth to evaluate runs over ``inputs`` with, and the span (s) that decides
    whether they are a long traverse (:func:`run_span_s`: the truth's, else the stream's)."""
    from fgslam.inputs import truth_of

    gt = truth_of(inputs)
    return gt, run_span_s(gt, inputs.measurements)


def check_window(cfg: LongTraverseConfig, worst_latency_s: float, margin_s: float) -> None:
    """Raise LongTraverseError unless the window holds a fix ``worst_latency_s`` late with
    ``margin_s`` to spare (the smoother's ``fixes.window_margin_s``)."""
    if cfg.isam2_fixed_lag_s <= worst_latency_s + margin_s:
        raise LongTraverseError(
            f"long_traverse.isam2_fixed_lag_s {cfg.isam2_fixed_lag_s:g} s is not longer than the worst fix "
            f"latency {worst_latency_s:g} s plus the window margin {margin_s:g} s: fixes would be lost to the window")


def _long_settings(name: str, cfg: LongTraverseConfig, overrides: dict | None = None) -> dict:
    """What back-end ``name`` gets on a long traverse (empty for one that gets nothing), as a
    nested mapping of the back-end's config; iSAM2's frame and persistence intervals follow the
    keyframe interval of ``overrides`` where they set one."""
    kf = cfg.isam2_keyframe_interval_s
    if has_setting(overrides, ("keyframes", "interval_s")):
        kf = float(overrides["keyframes"]["interval_s"])
    return {"isam2": {"fixed_lag_s": cfg.isam2_fixed_lag_s, "calibration_mode": cfg.isam2_calibration_mode,
                      "fixes": {"correlation_model": cfg.isam2_fix_correlation_model},
                      "odometry": {"slip_sigma": cfg.isam2_slip_sigma},
                      "keyframes": {"interval_s": kf},
                      "landmarks": {"min_frame_interval_s": FRAMES_PER_KEYFRAME * kf,
                                    "association": {"persistence_s": PERSISTENCE_FRAMES * kf}}},
            "ekf": {"forget_distance_m": cfg.ekf_forget_distance_m,
                    "trajectory_period_s": cfg.ekf_trajectory_period_s,
                    "keep_seen_s": cfg.ekf_keep_seen_s}}.get(name, {})


def _leaves(tree: dict, prefix: tuple[str, ...] = ()):
    """(path, value) of every leaf of a nested mapping."""
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _leaves(v, (*prefix, k))
        else:
            yield (*prefix, k), v


def has_setting(tree: dict | None, path: tuple[str, ...]) -> bool:
    """Whether the nested mapping ``tree`` sets ``path`` (a leaf, or a section above it)."""
    node = tree
    for k in path:
        if not isinstance(node, dict) or k not in node:
            return False
        node = node[k]
    return True


def drop_setting(tree: dict, path: tuple[str, ...]) -> None:
    """Remove ``path`` from the nested mapping ``tree`` where it is set (in place)."""
    *parents, leaf = path
    node = tree
    for k in parents:
        node = node.get(k) if isinstance(node, dict) else None
    if isinstance(node, dict):
        node.pop(leaf, None)


def per_world_keys(name: str) -> frozenset[tuple[str, ...]]:
    """The settings of back-end ``name`` (paths into its config) that :func:`backend_overrides_for`
    decides per stream (a comparison's worlds may be long or short): a saved config that wrote
    them out as explicit values would take them from the long-traverse rule when given back."""
    return frozenset(path for path, _ in _leaves(_long_settings(name, LongTraverseConfig())))


def backend_overrides_for(name: str, overrides: dict | None, duration_s: float,
                          cfg: LongTraverseConfig) -> dict | None:
    """The overrides back-end ``name`` runs with on a stream of ``duration_s``: on a long
    traverse iSAM2 gets ``fixed_lag_s``, ``calibration_mode``, its fixes' correlation model, its keyframe interval and the rock
    frame and persistence intervals that follow it (:class:`LongTraverseConfig`) and the EKF ``forget_distance_m``,
    ``trajectory_period_s`` and ``keep_seen_s``, each unless the overrides set it (setting by
    setting: an override of ``landmarks.association_cov_scale`` leaves the frame interval to the
    rule); otherwise unchanged."""
    defaults = _long_settings(name, cfg, overrides)
    if not defaults or not is_long(duration_s, cfg):
        return overrides
    out = merged_overrides(defaults, overrides or {})
    return overrides if out == (overrides or {}) else out

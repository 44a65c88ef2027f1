"""Side-by-side comparison: EKF and iSAM2, each with and without relocalization, on the same inputs.

Fairness: the fix list is computed once, in a reference pass (``reference_backend`` with online
relocalization on its own map), and the very same fixes (same ``t_meas``, ``t_recv``, values and
covariances) are replayed to every back-end; the reference back-end's own "with relocalization"
run is that reference pass (a replay would be identical). A dead-reckoning pass gives the
odometry-only curve.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fgslam import metrics as M
from fgslam.errors import FgslamError
from fgslam.fix_sources import FixProducer, relocalizers_for
from fgslam.inputs import RunInputs
from fgslam.io.image_rocks import ImageInputConfig
from fgslam.long_traverse import (
    LongTraverseConfig,
    backend_overrides_for,
    check_window,
    drop_setting,
    evaluation_truth,
    has_setting,
    is_long,
    per_world_keys,
    runner_config_for,
)
from fgslam.passes import Pass, run_passes
from fgslam.relocalizer import FixAttempt, RelocalizerConfig
from fgslam.runner import RunnerConfig, RunResult
from fgslam.terrain_height import TerrainHeightConfig, with_heights
from reloc.backend import FixOutcome, Trajectory
from reloc.config import Positive, PositiveInt, checked

log = logging.getLogger(__name__)


class _CallableModule(type(sys.modules[__name__])):
    """``fgslam.compare(...)`` is the facade's :func:`fgslam.api.compare` (see ``fgslam``'s doc)."""

    def __call__(self, *args, **kwargs):
        from fgslam.api import compare

        return compare(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

DR_KEY = "dead_reckoning"  # the odometry-only pass, always run (not a compared variant)
LABELS = {"ekf": "EKF", "isam2": "iSAM2", "dr": "Dead reckoning"}


class CompareError(FgslamError):
    """A comparison cannot be made (no back-end, no ground truth for metrics)."""


@dataclass(frozen=True)
@checked(CompareError)
class CompareConfig:
    """Which back-ends, the reference pass for the shared fixes, and the stage configs."""

    backends: tuple[str, ...] = ("ekf", "isam2")
    reference_backend: str = "isam2"
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    relocalizer: RelocalizerConfig = field(default_factory=RelocalizerConfig)  # the rocks' relocalizer
    kind_relocalizers: dict = field(default_factory=dict)  # other landmark kinds' relocalizer settings, by kind
    backend_overrides: dict = field(default_factory=dict)  # name -> config overrides
    rpe_delta_m: Positive = 10.0
    # back-end passes at once on forked processes (1: in this process, one after the other). None:
    # every pass at once, the cores shared by the OS: the short passes end early, the long ones
    # together, no core idles while one remains (the demo, 2 cores: comparison ~253-268 s with 2,
    # a pass without fixes running alone for its last ~44 s; 238 s at once, ~0.5 GB more memory)
    workers: PositiveInt | None = None
    topics: dict = field(default_factory=dict)  # input role -> bag topic (reloc.bag_spec.topic_names)
    images: ImageInputConfig = field(default_factory=ImageInputConfig)  # a bag's stereo images -> rocks
    long_traverse: LongTraverseConfig = field(default_factory=LongTraverseConfig)  # bounded back-ends
    # every pass starts from one draw of the start's claimed prior, seeded with the simulator's seed
    # (fgslam.inputs.start_drawn_from_prior): a Monte Carlo consistency test. False: the start as
    # read (a simulator's is the exact truth, claiming 1 cm and 0.002 rad it does not have)
    draw_start: bool = False
    # heights from the inputs' orbital terrain model on the fixes (fgslam.terrain_height)
    terrain_height: TerrainHeightConfig = field(default_factory=TerrainHeightConfig)

    def __post_init__(self) -> None:
        from fgslam.backends.registry import BACKEND_NAMES, backend_config
        from fgslam.inputs import bag_topics

        bag_topics(self.topics)  # an unknown role or a bad name is refused here, naming the roles

        unknown = [b for b in (*self.backends, self.reference_backend) if b not in BACKEND_NAMES]
        if unknown:
            raise CompareError(f"unknown back-end(s) {unknown} in backends/reference_backend; choose from {list(BACKEND_NAMES)}")
        for name, overrides in self.backend_overrides.items():
            backend_config(name, overrides, where=f"backend_overrides.{name}.")
        if "isam2" in self.backends:  # the window must hold the latest fix (fgslam.long_traverse)
            smoother = backend_config("isam2", self.backend_overrides.get("isam2"), where="backend_overrides.isam2.")
            check_window(self.long_traverse, self.relocalizer.delay_s, smoother.fixes.window_margin_s)


DR_OVERRIDES = {"build_map": False}  # the odometry-only pass needs no map


def resolved_compare_config(cfg: CompareConfig) -> dict:
    """``cfg`` as a plain dict with each compared back-end's *resolved* config (every value) in
    ``backend_overrides``, so the saved file reproduces the run when given back as overrides.

    Less the settings the long-traverse rule decides per world (:func:`fgslam.long_traverse.per_world_keys`:
    iSAM2's window, the EKF's forgetting), unless ``cfg`` set them: written out as the back-end's
    default (iSAM2 ``fixed_lag_s: 0``) they would be explicit when given back and win over the
    rule, turning a kilometre world's fixed-lag smoother into a full-history one. The values each
    world ran with are in results.json (``backend_overrides`` per world)."""
    from fgslam.backends.registry import resolved_config
    from reloc.config import config_to_dict

    out = config_to_dict(cfg)
    out["backend_overrides"] = {}
    for name in cfg.backends:
        given = cfg.backend_overrides.get(name) or {}
        resolved = resolved_config(name, given)
        for path in per_world_keys(name):
            if not has_setting(given, path):
                drop_setting(resolved, path)
        out["backend_overrides"][name] = resolved
    return out


def resolved_dead_reckoning_config() -> dict:
    """The resolved config of the comparison's dead-reckoning pass."""
    from fgslam.backends.registry import resolved_config

    return resolved_config("dr", DR_OVERRIDES)


def run_key(backend: str, reloc: bool) -> str:
    """Entity-safe key of a variant: "ekf", "ekf_reloc", "isam2", "isam2_reloc"."""
    return f"{backend}_reloc" if reloc else backend


def run_label(key: str) -> str:
    """Human label of a variant key ("iSAM2 + reloc")."""
    name, _, rel = key.partition("_")
    return LABELS.get(name, name) + (" + reloc" if rel else "")


def fixes_of(attempts: list[FixAttempt]):
    """The fixes produced by a list of attempts, in time order."""
    return [a.fix for a in attempts if a.fix is not None]


HEALTH_KEYS = ("n_failed_updates", "n_recoveries", "n_qr_retries", "factorization", "n_cholesky_returns", "n_compactions")


def attempts_by_status(attempts: list[FixAttempt]) -> dict[str, dict[str, int]]:
    """Attempts counted per relocalizer (its kinds, "+"-joined) and status ("fix", "no match",
    "too few landmarks", ...; a status's parenthesised detail left out), in order of appearance."""
    out: dict[str, dict[str, int]] = {}
    for a in attempts:
        by = out.setdefault(a.source or "rocks", {})
        status = a.status.split(" (")[0]
        by[status] = by.get(status, 0) + 1
    return out


def first_fix_s(outcomes: list[FixOutcome], t_start: float) -> list[float] | None:
    """Time to first fix, [measured, applied] seconds after ``t_start``: the accepted fix the
    back-end was given first (a held fix counts from when its second released it); None if none."""
    first = min((o for o in outcomes if o.accepted), key=lambda o: o.applied_s, default=None)
    return None if first is None else [first.fix.t_meas - t_start, first.applied_s - t_start]


def run_metrics(res: RunResult, gt: Trajectory | None, attempts: list[FixAttempt], rpe_delta_m: float) -> dict:
    """All metrics of one run as a JSON-ready dict (accuracy only with ground truth)."""
    out: dict = {
        "backend": res.backend,
        "runtime": {
            "wall_s": res.wall_s, "backend_s": res.backend_s, "match_s": res.match_s,
            "duration_s": res.duration_s, "real_time_factor": M.real_time_factor(res.duration_s, res.wall_s),
            "frame_latency": res.extra.get("frame_latency", {}),
            # the per-frame update: the EKF's landmark update; iSAM2's keyframe or fix update
            "update_p99_ms": res.stats.extra.get("latency_p99_ms", res.extra.get("frame_latency", {}).get("p99_ms")),
            # every frame's update, CPU time of its thread: the cost without the machine's other load
            "frame_cpu_latency": res.extra.get("frame_cpu_latency", {}),
            "frame_cpu_p99_ms": res.extra.get("frame_cpu_latency", {}).get("p99_ms"),
            "heap_trim": res.extra.get("heap_trim", {}),  # free memory handed back to the OS (RunnerConfig)
        },
        "memory": res.extra.get("memory", []),
        "slip": res.extra.get("slip", {}),  # the wheel-slip monitor's checks and spells (reloc.slip)
        "gyro": res.extra.get("gyro", {}),  # the gyro monitor's checks and bias spells (reloc.gyro)
        "n_landmarks": res.n_landmarks,
        "landmarks_by_kind": {k: len(m) for k, m in res.landmarks.items()},
    }
    fixes = res.fixes_sent
    accepted_t = {(o.fix.t_meas, o.fix.t_recv) for o in res.outcomes if o.accepted}
    acc = np.array([(f.t_meas, f.t_recv) in accepted_t for f in fixes], dtype=bool)
    out["fixes"] = M.fix_stats(
        len(attempts), np.array([f.xyyaw for f in fixes]).reshape(-1, 3),
        np.array([f.t_meas for f in fixes]), np.array([f.t_recv for f in fixes]), acc, gt, res.duration_s,
        cov_xyyaw=np.array([f.cov_xyyaw for f in fixes]).reshape(-1, 3, 3),
        cov_alone_xyyaw=np.array([sum(f.split_cov()) for f in fixes]).reshape(-1, 3, 3),
    ).to_dict()
    out["fixes"]["heights"] = M.fix_height_stats(fixes, gt)  # fixes with a height from the DEM
    out["fixes"]["heights"]["refused"] = int(res.stats.extra.get("n_heights_refused", 0))
    out["fixes"]["tracked"] = sum(1 for a in attempts if a.fix is not None and a.tracked)
    out["fixes"]["attempts_by_status"] = attempts_by_status(attempts)
    out["fixes"]["first_fix_s"] = first_fix_s(res.outcomes, res.t_start)
    out["reanchors"] = res.stats.extra.get("reanchors", [])
    out["fix_rejections"] = sorted({o.reason for o in res.outcomes if not o.accepted})
    out["fix_reject_reasons"] = res.stats.extra.get("fix_reject_reasons", {})
    out["fix_hold"] = res.stats.extra.get("fix_hold", {})  # far fixes held, released, dropped (fgslam.fix_hold)
    out["n_fixes_older_than_window"] = int(res.stats.extra.get("n_fixes_older_than_window", 0))
    # the solver's failures and recoveries (iSAM2: keyframe updates rolled back and retried without
    # their landmark factors, rebuilds, Cholesky -> QR spells): a run that had any is not a clean run
    health = {k: res.stats.extra[k] for k in HEALTH_KEYS if k in res.stats.extra}
    if health:
        out["solver_health"] = health
        if health.get("n_failed_updates", 0) or health.get("n_recoveries", 0):
            log.warning("%s: %d failed updates, %d solver recoveries (metrics.json solver_health)", res.backend,
                        health.get("n_failed_updates", 0), health.get("n_recoveries", 0))
    if res.stats.extra.get("calibration"):  # the back-end's estimated stereo calibration
        out["calibration"] = res.stats.extra["calibration"]
    if gt is None:
        return out
    out["ate"] = M.ate(res.final, gt).to_dict()
    planar, height = M.ate_parts(res.final, gt)
    out["ate_planar"], out["height_error"] = planar.to_dict(), height.to_dict()
    out["ate_se2_aligned"] = M.ate(res.final, gt, align_se2=True).to_dict()
    out["ate_online"] = M.ate(res.online, gt).to_dict()
    out["drift_pct"] = M.drift_pct(res.final, gt)  # final planar error per distance travelled
    out["rpe"] = M.rpe(res.final, gt, rpe_delta_m, "m").to_dict()  # as evo_rpe --delta D --delta_unit m
    cons, _ = M.consistency(res.online, gt)
    out["consistency"] = cons.to_dict()
    if res.final.cov is not None and len(res.final):
        out["consistency_final"] = M.consistency(res.final, gt)[0].to_dict()
    return out


def relocalizer_set(inputs: RunInputs, cfg: CompareConfig) -> list[FixProducer]:
    """The relocalizers of a run: one per catalog of ``inputs``, rocks with ``cfg.relocalizer``,
    the other kinds with ``cfg.kind_relocalizers[name]``; their fixes carry heights where the
    inputs have a terrain model (``cfg.terrain_height``)."""
    configs = dict(cfg.kind_relocalizers)
    if "rocks" in inputs.catalogs:
        configs["rocks"] = cfg.relocalizer
    return with_heights(relocalizers_for(inputs.catalogs, configs), inputs.dem, cfg.terrain_height)


@dataclass
class WorldComparison:
    """The comparison on one input: runs by key (see :func:`run_key`), the dead-reckoning run,
    the reference attempts (shared fixes), ground truth, metrics and total wall time."""

    inputs: RunInputs
    gt: Trajectory | None
    dr: RunResult
    runs: dict[str, RunResult]
    attempts: list[FixAttempt]
    metrics: dict
    wall_s: float


def _with_drawn_start(inputs: RunInputs) -> RunInputs:
    """``inputs`` with its start drawn from the start's prior (``CompareConfig.draw_start``)."""
    from fgslam.inputs import start_drawn_from_prior

    seed = inputs.source.get("seed")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise CompareError(f"{inputs.name}: draw_start needs the simulator's seed (a `fgslam sim` directory's "
                           f"world.yaml, a campaign's task); these inputs have {seed!r}")
    return dataclasses.replace(inputs, initial=start_drawn_from_prior(inputs.initial, seed))


def compare_world(
    inputs: RunInputs,
    config: CompareConfig | None = None,
    on_progress: Callable[[str, float], None] | None = None,
    relocalizers: list[FixProducer] | None = None,
) -> WorldComparison:
    """Run dead reckoning, the reference pass, and every back-end with and without the shared
    fixes; the reference pass relocalizes with ``relocalizers`` (default: one per catalog of the
    inputs, :func:`fgslam.fix_sources.relocalizers_for`)."""
    cfg = config or CompareConfig()
    if not cfg.backends:
        raise CompareError("no back-end to compare")
    if cfg.reference_backend not in cfg.backends:
        raise CompareError(f"reference_backend {cfg.reference_backend!r} is not among {cfg.backends}")
    wall0 = time.perf_counter()
    if cfg.draw_start:
        inputs = _with_drawn_start(inputs)
    gt, span = evaluation_truth(inputs)

    relocs = relocalizers if relocalizers is not None else relocalizer_set(inputs, cfg)
    ref_key = run_key(cfg.reference_backend, True)
    overrides = {name: backend_overrides_for(name, cfg.backend_overrides.get(name), span, cfg.long_traverse)
                 for name in cfg.backends}
    passes = [Pass(DR_KEY, "dr", DR_OVERRIDES, "none", "dead reckoning")]
    for name in cfg.backends:
        for with_reloc in (False, True):
            key = run_key(name, with_reloc)
            mode = "online" if key == ref_key else ("replay" if with_reloc else "none")
            label = run_label(key) + (" (reference)" if mode == "online" else "")
            passes.append(Pass(key, name, overrides[name], mode, label))
    runner = runner_config_for(cfg.runner, span, cfg.long_traverse)
    runs = run_passes(inputs, passes, runner, relocs, lambda r: fixes_of(r.attempts), cfg.workers, on_progress)
    dr = runs.pop(DR_KEY)
    attempts = runs[ref_key].attempts
    ordered = {run_key(n, r): runs[run_key(n, r)] for n in cfg.backends for r in (False, True)}
    met = {k: run_metrics(r, gt, attempts if k.endswith("_reloc") else [], cfg.rpe_delta_m) for k, r in ordered.items()}
    met[DR_KEY] = run_metrics(dr, gt, [], cfg.rpe_delta_m)
    wall = time.perf_counter() - wall0
    duration = dr.duration_s
    summary = {
        "name": inputs.name,
        "source": inputs.source,
        "duration_s": duration,
        "distance_m": M.path_length_m(gt.positions_m) if gt is not None else float("nan"),
        "wall_s": wall,
        "real_time_factor": M.real_time_factor(duration, wall),
        "matcher_build_s": sum(r.build_time_s for r in relocs),
        "shared_front_end_s": dr.extra.get("shared_front_end_s"),  # the passes' front-end, computed once
        "reference_backend": cfg.reference_backend,
        "long_traverse": is_long(span, cfg.long_traverse),
        "backend_overrides": overrides,
        "record_rate_hz": runner.record_rate_hz,  # the runner's, as the long traverse left it
        "runs": met,
    }
    if gt is not None:
        base = met[run_key(cfg.backends[0], False)]["ate"]["rmse"]
        for k in ordered:
            summary["runs"][k]["ate_improvement_over_own_pct"] = M.improvement_pct(
                met[run_key(k.split("_")[0], False)]["ate"]["rmse"], met[k]["ate"]["rmse"])
            summary["runs"][k][f"ate_improvement_over_{cfg.backends[0]}_pct"] = M.improvement_pct(base, met[k]["ate"]["rmse"])
    return WorldComparison(inputs, gt, dr, ordered, attempts, summary, wall)

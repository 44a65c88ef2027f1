"""iSAM2 smoother benchmarks: a long traverse with late fixes (real-time factor on one core,
per-update latency, ATE without / with good / with 10 % wrong fixes, next to the EKF), and a long
fixed-lag traverse (latency and memory against distance). Pure computation; the CLI prints/saves.

Fixes are synthetic (ground truth + noise, 1-30 s late); wrong ones are offset by 5-20 m.
"""

from __future__ import annotations

import itertools
import resource
import time
from collections.abc import Callable

import numpy as np

from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.synthetic import (
    SyntheticConfig,
    SyntheticRun,
    ate_m,
    drive,
    simulate_synthetic,
    synthetic_fixes,
)
from reloc.config import config_to_dict
from reloc.measurements import ImuSample, RockObservations


def rss_mb() -> float:
    """Resident set size of this process now (MB), from /proc (peak RSS where /proc is absent)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * resource.getpagesize() / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def make_scenario(source: str, seed: int, duration_s: float, world: str = "my2021",
                  speed_mps: float = 0.15) -> SyntheticRun:
    """A traverse from the simulator (``source`` "sim") or the synthetic generator ("synthetic")."""
    if source == "sim":
        from sim.config import SimConfig, TraverseConfig
        from sim.simulate import simulate

        run = simulate(SimConfig(world=world, seed=seed, traverse=TraverseConfig(duration_s=duration_s)))
        return SyntheticRun(run.measurements, np.asarray(run.ground_truth.t), np.asarray(run.ground_truth.T_world_base),
                            np.zeros((0, 3)), run.initial_pose)
    if source != "synthetic":
        raise ValueError(f"source must be 'sim' or 'synthetic', got {source!r}")
    return simulate_synthetic(SyntheticConfig(seed=seed, duration_s=duration_s, speed_mps=speed_mps))


def _backend(kind: str, run: SyntheticRun, cfg: SmootherConfig):
    if kind == "isam2":
        return Isam2Smoother(run.initial_pose, cfg)
    from ekf.slam import EkfSlam

    return EkfSlam(run.initial_pose)


def run_case(kind: str, run: SyntheticRun, fixes: list, cfg: SmootherConfig, progress=None) -> dict:
    """One back-end over one scenario: timing, latency (iSAM2), ATE of the final and causal estimates."""
    be = _backend(kind, run, cfg)
    out = drive(be, run.measurements, [f for f, _ in fixes], progress=progress)
    tr = be.trajectory()
    duration = float(run.gt_t[-1] - run.gt_t[0])
    wrong_t = {f.t_meas for f, w in fixes if w}
    res = {
        "backend": kind,
        "backend_s": out.backend_s,
        "backend_cpu_s": out.backend_cpu_s,
        "real_time_factor": duration / out.backend_s,
        "real_time_factor_cpu": duration / max(out.backend_cpu_s, 1e-9),
        "ate_final_m": ate_m(run, tr.t, tr.T_world_base),
        "ate_online_m": ate_m(run, out.est_t, out.est_T),
        "n_fixes": len(fixes),
        "n_wrong": len(wrong_t),
        "n_accepted": sum(o.accepted for o in out.outcomes),
        "n_wrong_accepted": sum(o.accepted for o in out.outcomes if o.fix.t_meas in wrong_t),
    }
    st = be.stats()
    if kind == "isam2":
        lat = np.array(be.update_latency_s) * 1e3
        lat_cpu = np.array(be.update_cpu_s) * 1e3
        res.update({
            "n_updates": int(lat.size),
            "latency_median_ms": float(np.median(lat)),
            "latency_p99_ms": float(np.percentile(lat, 99)),
            "latency_max_ms": float(lat.max()),
            "latency_cpu_median_ms": float(np.median(lat_cpu)),
            "latency_cpu_p99_ms": float(np.percentile(lat_cpu, 99)),
            "n_keyframes": st.extra["n_keyframes"],
            "n_landmarks": st.n_landmarks,
            "n_retracted": len(st.extra["retracted_fixes"]),
            "n_wrong_retracted": sum(r["t_meas"] in wrong_t for r in st.extra["retracted_fixes"]),
        })
    return res


def traverse_benchmark(run: SyntheticRun, seed: int, cfg: SmootherConfig, with_ekf: bool = True,
                       progress: Callable[[str], None] | None = None) -> dict:
    """No fixes / good fixes / +10 % wrong fixes, for the smoother (and the EKF when available)."""
    cases = {
        "no_fixes": [],
        "fixes": synthetic_fixes(run, np.random.default_rng(seed + 100)),
        "fixes_10pct_wrong": synthetic_fixes(run, np.random.default_rng(seed + 100), wrong_fraction=0.1),
    }
    kinds = ["isam2"]
    if with_ekf:
        try:
            import ekf.slam  # noqa: F401

            kinds.append("ekf")
        except ImportError:
            pass
    out: dict = {
        "duration_s": float(run.gt_t[-1] - run.gt_t[0]),
        "distance_m": float(np.sum(np.linalg.norm(np.diff(run.gt_T[:, :3, 3], axis=0), axis=1))),
        "n_imu": sum(isinstance(m, ImuSample) for m in run.measurements),
        "n_rock_frames": sum(isinstance(m, RockObservations) for m in run.measurements),
        "runs": [],
    }
    for kind in kinds:
        for name, fixes in cases.items():
            if progress:
                progress(f"{kind} / {name}")
            r = run_case(kind, run, fixes, cfg)
            r["case"] = name
            out["runs"].append(r)
    return out


def fixed_lag_benchmark(distance_m: float, seed: int, lag_s: float, speed_mps: float = 0.3,
                        n_bins: int = 10, progress: Callable[[float], None] | None = None) -> dict:
    """Synthetic traverse of ``distance_m`` in fixed-lag mode with fixes; latency and memory per
    distance bin (RSS sampled as the run goes)."""
    run = simulate_synthetic(SyntheticConfig(seed=seed, duration_s=distance_m / speed_mps, speed_mps=speed_mps))
    fixes = synthetic_fixes(run, np.random.default_rng(seed + 7))
    cfg = SmootherConfig(fixed_lag_s=lag_s)
    sm = Isam2Smoother(run.initial_pose, cfg)
    seg = np.linalg.norm(np.diff(run.gt_T[:, :3, 3], axis=0), axis=1)
    dist = np.concatenate([[0.0], np.cumsum(seg)])
    samples: list[tuple[float, float, int, int]] = []  # (t, rss_mb, n_updates, n_alive_keys)

    def hook(t: float) -> None:
        samples.append((t, rss_mb(), len(sm.update_latency_s), len(sm.solver._alive)))
        if progress:
            progress(t)

    t0 = time.perf_counter()
    out = drive(sm, run.measurements, [f for f, _ in fixes], progress=hook)
    wall = time.perf_counter() - t0
    hook(float(run.gt_t[-1]))
    lat_ms = np.array(sm.update_latency_s) * 1e3
    cpu_ms = np.array(sm.update_cpu_s) * 1e3
    kf_t = np.array(sm.kfs.t[1:])
    # the i-th latency belongs to a keyframe or a fix; place each at the distance of its sample index
    upd_t = np.interp(np.arange(lat_ms.size), [s[2] for s in samples], [s[0] for s in samples])
    upd_d = np.interp(upd_t, run.gt_t, dist)
    edges = np.linspace(0.0, dist[-1], n_bins + 1)
    bins = []
    for a, b in itertools.pairwise(edges):
        m = (upd_d >= a) & (upd_d < b) if b < edges[-1] else (upd_d >= a)
        s_d = np.interp([s[0] for s in samples], run.gt_t, dist)
        in_bin = [s for s, d in zip(samples, s_d) if a <= d <= b]
        bins.append({
            "distance_m": float(b),
            "n_updates": int(m.sum()),
            "latency_median_ms": float(np.median(lat_ms[m])) if m.any() else float("nan"),
            "latency_p99_ms": float(np.percentile(lat_ms[m], 99)) if m.any() else float("nan"),
            "latency_cpu_median_ms": float(np.median(cpu_ms[m])) if m.any() else float("nan"),
            "latency_cpu_p99_ms": float(np.percentile(cpu_ms[m], 99)) if m.any() else float("nan"),
            "rss_mb": float(max(s[1] for s in in_bin)) if in_bin else float("nan"),
            "alive_keys": int(max(s[3] for s in in_bin)) if in_bin else -1,
        })
    tr = sm.trajectory()
    return {
        "distance_m": float(dist[-1]),
        "duration_s": float(run.gt_t[-1]),
        "lag_s": lag_s,
        "wall_s": wall,
        "backend_s": out.backend_s,
        "real_time_factor": float(run.gt_t[-1]) / out.backend_s,
        "real_time_factor_cpu": float(run.gt_t[-1]) / max(out.backend_cpu_s, 1e-9),
        "latency_cpu_median_ms": float(np.median(cpu_ms)),
        "latency_cpu_p99_ms": float(np.percentile(cpu_ms, 99)),
        "n_keyframes": len(sm.kfs),
        "n_keyframes_timed": int(kf_t.size),
        "latency_median_ms": float(np.median(lat_ms)),
        "latency_p99_ms": float(np.percentile(lat_ms, 99)),
        "ate_final_m": ate_m(run, tr.t, tr.T_world_base),
        "n_fixes": len(fixes),
        "n_accepted": sum(o.accepted for o in out.outcomes),
        "bins": bins,
        "config": config_to_dict(cfg),
    }

"""``fgslam bench match``: success, false matches, accuracy and speed of the constellation matcher,
side by side with astroalign on the very same queries (see docs/matcher.md).

Success: the recovered transform puts the local map's centroid (where the rover is) within
0.5 m of the truth and the heading within 3 deg. False match: any answer to a query cut from a
field that is not in the catalog. Accuracy: median position error over successes against the
median of sigma / sqrt(n_inliers) (the error of a centroid estimated from n_inliers points).
Query times are the CPU time of the calling thread (the matcher is single-threaded), so that a
busy machine does not inflate them; the wall-clock median is reported next to them.

Size: ~380 lines, above the project's ~300, for a reason: one benchmark whose rows (field
sizes, the runner's map snapshots, detector catalogs, astroalign on the very same queries) share
the query records and the summary; the scenarios themselves are in
:mod:`fgslam.bench.match_scenarios`.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import resource
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fgslam.bench.match_scenarios import (
    Query,
    detector_catalog,
    detector_query,
    make_field,
    make_query,
    runner_query,
)

__all__ = ["MatchBenchConfig", "result_tables", "run_match_bench"]

POS_OK_M = 0.5
HEADING_OK_DEG = 3.0
CAT_P, CAT_R = 0.44, 0.364  # published orbital detector quality
LOC_P, LOC_R = 0.744, 0.692  # published rover detector quality

Progress = Callable[[str, int], Callable[[], None]]


@dataclass(frozen=True)
class MatchBenchConfig:
    """Benchmark settings; ``queries`` per (size, layout, sigma); astroalign runs on the first
    ``astro_queries`` of them for sizes in ``astro_sizes`` (a try longer than ``astro_timeout_s``
    of wall time counts as no answer). The runner-like setting matches ``runner_queries`` local
    maps of 80 rocks against a ``runner_size``-rock catalog with a prior of
    ``runner_prior_radius_m``, as the relocalizer does."""

    sizes: tuple[int, ...] = (300, 3000, 100_000)
    layouts: tuple[str, ...] = ("uniform", "clustered")
    sigmas_m: tuple[float, ...] = (0.05, 0.2)
    queries: int = 500
    outside_queries: int = 1000
    detector_size: int = 3000
    detector_queries: int = 300
    detector_sigma_m: float = 0.05
    astro_queries: int = 20
    astro_sizes: tuple[int, ...] = (300, 3000)
    astro_timeout_s: float = 30.0
    runner_size: int = 2259
    runner_queries: int = 300
    runner_sigma_m: float = 0.12
    runner_prior_radius_m: float = 5.0
    build_size: int = 1_000_000
    seed: int = 0


def quick_config(seed: int = 0) -> MatchBenchConfig:
    """A small run (about a minute) for smoke tests."""
    return MatchBenchConfig(
        sizes=(300, 3000), layouts=("uniform", "clustered"), sigmas_m=(0.05, 0.2), queries=40,
        outside_queries=40, detector_queries=30, astro_queries=4, astro_sizes=(300,), runner_queries=30,
        build_size=100_000, seed=seed,
    )


def _errors(theta: float, t: np.ndarray, scale: float, q: Query) -> tuple[float, float]:
    """Position error (m) at the local map's centroid and heading error (deg) of an estimate."""
    c = q.local_xy.mean(axis=0)
    rot = lambda a: np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    true_w = rot(q.theta_rad) @ c + q.t
    est_w = scale * rot(theta) @ c + t
    dth = (theta - q.theta_rad + np.pi) % (2 * np.pi) - np.pi
    return float(np.hypot(*(est_w - true_w))), float(abs(np.degrees(dth)))


def _ours(matcher, q: Query) -> dict:
    t0, c0 = time.perf_counter(), time.thread_time()
    res = matcher.match(q.local_xy, q.local_size)
    dt, cpu = time.perf_counter() - t0, time.thread_time() - c0
    if res is None:
        return {"found": False, "time_s": dt, "cpu_s": cpu}
    e, h = _errors(res.rotation_rad, res.translation, res.scale, q)
    return {"found": True, "time_s": dt, "cpu_s": cpu, "pos_err_m": e, "head_err_deg": h, "n_inliers": res.n_inliers}


def _theirs_worker(catalog_xy: np.ndarray, local_xy: np.ndarray, tol_m: float) -> tuple[np.ndarray | None, float]:
    """astroalign's transform params (3, 3) (None: it found none) and its CPU time."""
    import astroalign

    astroalign.PIXEL_TOL = tol_m  # same inlier tolerance as ours, in metres
    c0 = time.thread_time()
    try:
        tf, _ = astroalign.find_transform(local_xy, catalog_xy, max_control_points=catalog_xy.shape[0])
    except Exception:  # noqa: BLE001 -- MaxIterError, ValueError...: astroalign found no transform
        return None, time.thread_time() - c0
    return np.asarray(tf.params), time.thread_time() - c0


class _Astro:
    """astroalign in a forked worker process, so that a try can be abandoned after a timeout."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.pool = None

    def __call__(self, catalog_xy: np.ndarray, q: Query, tol_m: float) -> dict:
        import multiprocessing

        if self.pool is None:
            self.pool = multiprocessing.get_context("fork").Pool(1)
        t0 = time.perf_counter()
        job = self.pool.apply_async(_theirs_worker, (catalog_xy, q.local_xy, tol_m))
        try:
            params, cpu = job.get(timeout=self.timeout_s)
        except multiprocessing.TimeoutError:
            self.close()
            dt = time.perf_counter() - t0
            return {"found": False, "time_s": dt, "cpu_s": dt, "timed_out": True}
        dt = time.perf_counter() - t0
        if params is None:
            return {"found": False, "time_s": dt, "cpu_s": cpu}
        theta = float(np.arctan2(params[1, 0], params[0, 0]))
        e, h = _errors(theta, params[:2, 2], float(np.hypot(params[0, 0], params[1, 0])), q)
        return {"found": True, "time_s": dt, "cpu_s": cpu, "pos_err_m": e, "head_err_deg": h, "n_inliers": 0}

    def close(self) -> None:
        if self.pool is not None:
            self.pool.terminate()
            self.pool.join()
            self.pool = None


def _summary(rows: list[dict], sigma_m: float | None = None) -> dict:
    n = len(rows)
    ok = [r for r in rows if r["found"] and r["pos_err_m"] < POS_OK_M and r["head_err_deg"] < HEADING_OK_DEG]
    found = sum(r["found"] for r in rows)
    times = np.array([r["cpu_s"] for r in rows]) if rows else np.zeros(1)
    wall = np.array([r["time_s"] for r in rows]) if rows else np.zeros(1)
    out = {
        "queries": n,
        "success_pct": 100.0 * len(ok) / max(n, 1),
        "no_answer_pct": 100.0 * (n - found) / max(n, 1),
        "wrong_pct": 100.0 * (found - len(ok)) / max(n, 1),
        "median_err_m": float(np.median([r["pos_err_m"] for r in ok])) if ok else math.nan,
        "median_head_err_deg": float(np.median([r["head_err_deg"] for r in ok])) if ok else math.nan,
        "median_ms": 1e3 * float(np.median(times)),
        "p99_ms": 1e3 * float(np.percentile(times, 99)),
        "median_wall_ms": 1e3 * float(np.median(wall)),
    }
    if sigma_m is not None and ok and ok[0].get("n_inliers"):
        bound = float(np.median([sigma_m / math.sqrt(r["n_inliers"]) for r in ok]))
        out["median_sigma_over_sqrt_k_m"] = bound
        out["accuracy_ratio"] = out["median_err_m"] / bound
    return out


def _build_stats(n: int, seed: int) -> dict:
    """Index build time and memory at ``n`` rocks: wall time, peak RSS growth, tracemalloc peak."""
    from reloc import Catalog

    field = make_field(n, "uniform", np.random.default_rng(seed))
    gc.collect()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0, c0 = time.perf_counter(), time.process_time()
    cat = Catalog(field.xy, field.size)
    build_s, build_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    rss_peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024.0
    n_tri, index_mb = cat.n_triangles, cat.nbytes / 1e6
    del cat
    gc.collect()
    tracemalloc.start()
    Catalog(field.xy, field.size)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {
        "rocks": n, "triangles": n_tri, "build_s": build_s, "build_cpu_s": build_cpu_s, "index_mb": index_mb,
        "rss_peak_growth_mb": rss_peak, "tracemalloc_peak_mb": peak / 1e6,
    }


def run_match_bench(cfg: MatchBenchConfig, progress: Progress | None = None) -> dict:
    """Run every benchmark setting of ``cfg``; returns plain data (JSON-serialisable)."""
    from reloc import Catalog, ConstellationMatcher, MatcherConfig

    tick = progress or (lambda name, total: (lambda: None))
    out: dict = {"config": dataclasses.asdict(cfg), "build": [], "known": [], "outside": [], "detector": [], "astro": []}
    out["build"].append(_build_stats(cfg.build_size, cfg.seed))  # first: the RSS peak is per process
    for size in cfg.sizes:
        for layout in cfg.layouts:
            rng = np.random.default_rng([cfg.seed, size, len(layout)])
            field = make_field(size, layout, rng)
            other = make_field(size, layout, rng, origin=(field.side_m + 1000.0, 0.0))
            cat = Catalog(field.xy, field.size)
            out["build"].append({"rocks": size, "layout": layout, "triangles": cat.n_triangles,
                                 "build_s": cat.build_time_s, "index_mb": cat.nbytes / 1e6})
            for sigma in cfg.sigmas_m:
                mcfg = MatcherConfig(sigma_m=sigma, seed=cfg.seed)
                matcher = ConstellationMatcher(cat, mcfg)
                qs = [make_query(field, rng, sigma, tree=cat.tree) for _ in range(cfg.queries)]
                step = tick(f"{size} {layout} sigma {sigma}", len(qs))
                ours = []
                for q in qs:
                    ours.append(_ours(matcher, q))
                    step()
                key = {"rocks": size, "layout": layout, "sigma_m": sigma}
                out["known"].append({**key, **_summary(ours, sigma)})
                if size in cfg.astro_sizes and cfg.astro_queries > 0:
                    out["astro"].append(
                        _astro_row(key, cat, qs[: cfg.astro_queries], ours, mcfg, tick, cfg.astro_timeout_s)
                    )
                from scipy.spatial import cKDTree

                otree = cKDTree(other.xy)
                oq = [make_query(other, rng, sigma, tree=otree) for _ in range(cfg.outside_queries)]
                step = tick(f"{size} {layout} sigma {sigma} outside", len(oq))
                found = 0
                for q in oq:
                    found += matcher.match(q.local_xy, q.local_size) is not None
                    step()
                out["outside"].append({**key, "queries": len(oq), "false_matches": found,
                                       "false_match_pct": 100.0 * found / max(len(oq), 1)})
    for layout in cfg.layouts if cfg.detector_queries > 0 else ():
        out["detector"].append(_detector_row(cfg, layout, tick, out))
    out["runner"] = [_runner_row(cfg, tick)] if cfg.runner_queries > 0 else []
    return out


def _runner_row(cfg: MatchBenchConfig, tick: Progress) -> dict:
    """Runner-like: 80-rock local maps in a drifted world frame, matched with a prior."""
    from reloc import Catalog, ConstellationMatcher, MatcherConfig
    from reloc.matcher import MatchPrior

    rng = np.random.default_rng([cfg.seed, 11])
    field = make_field(cfg.runner_size, "uniform", rng)
    cat = Catalog(field.xy, field.size)
    sig = cfg.runner_sigma_m
    matcher = ConstellationMatcher(cat, MatcherConfig(sigma_m=sig, seed=cfg.seed))
    qs = [runner_query(field, rng, sig, tree=cat.tree) for _ in range(cfg.runner_queries)]
    step = tick("runner-like (~80 rocks, prior)", len(qs))
    rows = []
    for q in qs:
        prior = MatchPrior(q.local_xy.mean(axis=0), cfg.runner_prior_radius_m)
        t0, c0 = time.perf_counter(), time.thread_time()
        res = matcher.match(q.local_xy, q.local_size, prior)
        dt, cpu = time.perf_counter() - t0, time.thread_time() - c0
        row = {"found": res is not None, "time_s": dt, "cpu_s": cpu}
        if res is not None:
            e, h = _errors(res.rotation_rad, res.translation, res.scale, q)
            row.update(pos_err_m=e, head_err_deg=h, n_inliers=res.n_inliers)
        rows.append(row)
        step()
    return {"rocks": len(cat), "sigma_m": sig, "prior_radius_m": cfg.runner_prior_radius_m,
            "local_rocks_mean": float(np.mean([q.local_xy.shape[0] for q in qs])), **_summary(rows, sig)}


def _astro_row(key: dict, cat, qs: list[Query], ours: list[dict], mcfg, tick: Progress, timeout_s: float) -> dict:
    step = tick(f"astroalign {key}", len(qs))
    theirs = []
    astro = _Astro(timeout_s)
    try:
        for q in qs:
            theirs.append(astro(cat.xy, q, mcfg.inlier_radius_m))
            step()
    finally:
        astro.close()
    a, b = _summary(ours[: len(qs)]), _summary(theirs)
    ratio = lambda x, y: x / y if y and not math.isnan(y) and not math.isnan(x) else math.nan
    return {
        **key, "queries": len(qs),
        "ours_success_pct": a["success_pct"], "astroalign_success_pct": b["success_pct"],
        "success_ratio": ratio(a["success_pct"], b["success_pct"]),
        "ours_median_err_m": a["median_err_m"], "astroalign_median_err_m": b["median_err_m"],
        "err_ratio": ratio(a["median_err_m"], b["median_err_m"]),
        "ours_median_ms": a["median_ms"], "astroalign_median_ms": b["median_ms"],
        "time_ratio": ratio(a["median_ms"], b["median_ms"]),
        "astroalign_wrong_pct": b["wrong_pct"],
        "astroalign_timeouts": sum(bool(r.get("timed_out")) for r in theirs), "astro_timeout_s": timeout_s,
    }


def _detector_row(cfg: MatchBenchConfig, layout: str, tick: Progress, out: dict) -> dict:
    from reloc import Catalog, ConstellationMatcher, MatcherConfig

    rng = np.random.default_rng([cfg.seed, 7, len(layout)])
    truth = make_field(cfg.detector_size, layout, rng)
    sig = cfg.detector_sigma_m
    orb = detector_catalog(truth, rng, precision=CAT_P, recall=CAT_R, sigma_m=sig, size_jitter=0.15)
    cat = Catalog(orb.xy, orb.size)
    mcfg = MatcherConfig(sigma_m=math.hypot(sig, sig), seed=cfg.seed)
    matcher = ConstellationMatcher(cat, mcfg)
    from scipy.spatial import cKDTree

    ttree = cKDTree(truth.xy)
    qs = [
        detector_query(truth, rng, n_local=80, precision=LOC_P, recall=LOC_R, sigma_m=sig, size_jitter=0.15, tree=ttree)
        for _ in range(cfg.detector_queries)
    ]
    step = tick(f"detector quality {layout}", len(qs))
    ours = []
    for q in qs:
        ours.append(_ours(matcher, q))
        step()
    key = {"truth_rocks": cfg.detector_size, "catalog_rocks": len(cat), "layout": layout, "sigma_m": sig,
           "local_rocks_mean": float(np.mean([q.local_xy.shape[0] for q in qs]))}
    if cfg.detector_size in cfg.astro_sizes and cfg.astro_queries > 0:
        out["astro"].append(_astro_row({"rocks": len(cat), "layout": f"{layout} detector", "sigma_m": sig},
                                       cat, qs[: cfg.astro_queries], ours, mcfg, tick, cfg.astro_timeout_s))
    return {**key, **_summary(ours, math.hypot(sig, sig))}


def result_tables(res: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, columns, rows of strings) for every table of a benchmark result."""
    f = lambda v, d=1: "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"
    tables = []
    b = res["build"]
    tables.append(("Index build", ["rocks", "layout", "triangles", "build s", "build CPU s", "index MB", "RSS peak growth MB", "tracemalloc peak MB"],
                   [[str(r["rocks"]), r.get("layout", "uniform"), str(r["triangles"]), f(r["build_s"], 2), f(r.get("build_cpu_s"), 2), f(r["index_mb"]),
                     f(r.get("rss_peak_growth_mb")), f(r.get("tracemalloc_peak_mb"))] for r in b]))
    tables.append(("Queries from the catalog area (40-rock disc, 30 % dropped, 10 % spurious)",
                   ["rocks", "layout", "sigma m", "queries", "success %", "no answer %", "wrong %", "median err m",
                    "sigma/sqrt(K) m", "err ratio", "median heading deg", "median ms", "p99 ms", "median wall ms"],
                   [[str(r["rocks"]), r["layout"], f(r["sigma_m"], 2), str(r["queries"]), f(r["success_pct"]),
                     f(r["no_answer_pct"]), f(r["wrong_pct"]), f(r["median_err_m"], 3),
                     f(r.get("median_sigma_over_sqrt_k_m"), 3), f(r.get("accuracy_ratio"), 2),
                     f(r["median_head_err_deg"], 2), f(r["median_ms"]), f(r["p99_ms"]), f(r["median_wall_ms"])]
                    for r in res["known"]]))
    tables.append(("Queries from outside the catalog (false matches)",
                   ["rocks", "layout", "sigma m", "queries", "false matches", "false match %"],
                   [[str(r["rocks"]), r["layout"], f(r["sigma_m"], 2), str(r["queries"]), str(r["false_matches"]),
                     f(r["false_match_pct"], 2)] for r in res["outside"]]))
    tables.append(("Published detector qualities (catalog P 0.44 / R 0.364, local P 0.744 / R 0.692, ~80 local rocks)",
                   ["truth rocks", "catalog rocks", "layout", "sigma m", "local rocks", "queries", "success %", "no answer %",
                    "wrong %", "median err m", "err ratio", "median ms", "p99 ms"],
                   [[str(r["truth_rocks"]), str(r["catalog_rocks"]), r["layout"], f(r["sigma_m"], 2),
                     f(r["local_rocks_mean"]), str(r["queries"]), f(r["success_pct"]), f(r["no_answer_pct"]),
                     f(r["wrong_pct"]), f(r["median_err_m"], 3), f(r.get("accuracy_ratio"), 2), f(r["median_ms"]),
                     f(r["p99_ms"])] for r in res["detector"]]))
    tables.append(("Side by side with astroalign (same queries, same inlier tolerance)",
                   ["rocks", "layout", "sigma m", "queries", "ours success %", "astroalign success %", "ratio",
                    "ours median err m", "astroalign median err m", "ratio", "ours median ms", "astroalign median ms",
                    "ratio", "astroalign wrong %", "astroalign timeouts"],
                   [[str(r["rocks"]), r["layout"], f(r["sigma_m"], 2), str(r["queries"]), f(r["ours_success_pct"]),
                     f(r["astroalign_success_pct"]), f(r["success_ratio"], 2), f(r["ours_median_err_m"], 3),
                     f(r["astroalign_median_err_m"], 3), f(r["err_ratio"], 2), f(r["ours_median_ms"]),
                     f(r["astroalign_median_ms"]), f(r["time_ratio"], 3), f(r["astroalign_wrong_pct"]),
                     f"{r.get('astroalign_timeouts', 0)} (> {r.get('astro_timeout_s', math.nan):.0f} s)"]
                    for r in res["astro"]]))
    tables.append(("Runner-like (80-rock local maps in a drifted world frame, matched with a prior)",
                   ["catalog rocks", "sigma m", "prior radius m", "local rocks", "queries", "success %",
                    "no answer %", "wrong %", "median err m", "err ratio", "median ms", "p99 ms", "median wall ms"],
                   [[str(r["rocks"]), f(r["sigma_m"], 2), f(r["prior_radius_m"]), f(r["local_rocks_mean"]),
                     str(r["queries"]), f(r["success_pct"]), f(r["no_answer_pct"]), f(r["wrong_pct"]),
                     f(r["median_err_m"], 3), f(r.get("accuracy_ratio"), 2), f(r["median_ms"]), f(r["p99_ms"]),
                     f(r["median_wall_ms"])] for r in res.get("runner", [])]))
    return tables


def tables_markdown(res: dict) -> str:
    """All tables as GitHub markdown."""
    parts = []
    for title, cols, rows in result_tables(res):
        parts.append(f"### {title}\n\n| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n")
        parts.append("".join("| " + " | ".join(r) + " |\n" for r in rows) + "\n")
    return "".join(parts)

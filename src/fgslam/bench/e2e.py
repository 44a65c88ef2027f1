"""``fgslam bench e2e``: one world, one seed, through both back-ends with statistical and with
image detections.

The simulator runs once; the image source is that same run with its /rocks frames and catalog
replaced by the image path (:func:`sim.image_detections.with_image_detections`: rendered stereo
pair -> rover detector -> SGBM; rendered orbital image -> nadir detector), so both sources share
the route, odometry, IMU and ground truth, exactly as ``fgslam sim`` with ``--detections
statistical`` and ``--detections image`` for the same seed. Each source is written as a
``fgslam sim`` directory and compared as ``fgslam compare`` does (EKF and iSAM2, each with and
without the same relocalization fixes). The table puts the two sources side by side.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable
from pathlib import Path

from fgslam.compare import DR_KEY, CompareConfig, run_key, run_label
from fgslam.report import _f, _jsonable

log = logging.getLogger(__name__)

SOURCES = ("statistical", "image")
Tick = Callable[[str, int], Callable[[], None]]
# compare_progress(inputs) -> context manager yielding on_progress(stage, t) (or None)
CompareProgress = Callable[[object], contextlib.AbstractContextManager]

_DETECTION_KEYS = ("n_stereo_frames", "n_visible", "n_detections", "stereo_precision", "stereo_recall", "n_rocks",
                   "n_catalog", "catalog_precision", "catalog_recall", "image_render_s_per_frame",
                   "image_detect_s_per_frame", "image_stereo_s_per_frame", "distance_m", "duration_s")


def run_e2e(sim_cfg, out: Path, compare_cfg: CompareConfig | None = None, image_cfg=None, tick: Tick | None = None,
            compare_progress: CompareProgress | None = None, rrd: bool = False) -> dict:
    """Simulate ``sim_cfg`` (:class:`sim.SimConfig`), derive the image-detection run, write both
    as ``out/statistical`` and ``out/image``, compare each, write ``out/compare/`` (the full
    comparison), ``out/table.md`` and ``out/results.json``; returns the results (plain data)."""
    from fgslam.compare import compare_world
    from fgslam.inputs import load_sim_dir
    from fgslam.io.sim_dir import write_sim_dir
    from fgslam.outputs import write_comparison
    from reloc.measurements import RockObservations
    from sim.image_detections import ImageDetectionConfig, with_image_detections
    from sim.simulate import simulate

    tick = tick or (lambda name, total: (lambda: None))
    compare_progress = compare_progress or (lambda inputs: contextlib.nullcontext(None))
    compare_cfg = compare_cfg or CompareConfig()
    image_cfg = image_cfg or ImageDetectionConfig()
    out = Path(out)
    step = tick(f"simulating {sim_cfg.world} (seed {sim_cfg.seed})", 1)
    runs = {"statistical": simulate(sim_cfg)}
    step()
    n_frames = sum(isinstance(m, RockObservations) for m in runs["statistical"].measurements)
    step = tick("image path: render + detect stereo frames", n_frames)
    runs["image"] = with_image_detections(runs["statistical"], image_cfg, progress=step)
    step = tick("writing both simulator directories", len(SOURCES))
    for name in SOURCES:
        write_sim_dir(runs[name], out / name, overwrite=True)  # this benchmark's own intermediate output
        step()
    comparisons = []
    for name in SOURCES:
        inputs = load_sim_dir(out / name)  # the bag and catalog, as `fgslam compare` reads them
        with compare_progress(inputs) as on_progress:
            comparisons.append(compare_world(inputs, compare_cfg, on_progress=on_progress))
    write_comparison(out / "compare", comparisons, compare_cfg, rrd=rrd)
    from reloc.config import config_to_dict

    res = {
        "world": str(sim_cfg.world), "seed": int(sim_cfg.seed),
        "stereo_rate_hz": float(sim_cfg.sensors.stereo.rate_hz),
        "sources": {name: {"detections": {k: runs[name].stats.get(k) for k in _DETECTION_KEYS},
                           "comparison": wc.metrics}
                    for name, wc in zip(SOURCES, comparisons)},
        "sim_config": config_to_dict(sim_cfg), "compare_config": config_to_dict(compare_cfg),
        "image_config": config_to_dict(image_cfg),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(_jsonable(res), indent=2))
    (out / "table.md").write_text(markdown(res))
    log.info("e2e: wrote %s", out)
    return res


def runs(comparison: dict) -> dict:
    """The variant metrics (by run key) of one source's comparison summary."""
    return comparison["runs"]


def table_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """(columns, rows): one row per quantity, one column per detection source."""
    sources = list(res["sources"])
    cols = ["quantity", *sources]
    rows: list[list[str]] = []

    def row(label: str, fn: Callable[[dict, dict], object], fmt: str = "{:.3f}") -> None:
        cells = []
        for s in sources:
            det, cmp_ = res["sources"][s]["detections"], res["sources"][s]["comparison"]
            try:
                v = fn(det, cmp_)
            except (KeyError, TypeError):
                v = None
            cells.append(v if isinstance(v, str) else _f(v, fmt))
        rows.append([label, *cells])

    ref = run_key(res["sources"][sources[0]]["comparison"].get("reference_backend", "isam2"), True)
    row("Traverse [m] / [s]", lambda d, c: f"{c['distance_m']:.1f} / {c['duration_s']:.0f}")
    row("Stereo frames", lambda d, c: d["n_stereo_frames"], "{:d}")
    row("Rock detections per frame", lambda d, c: d["n_detections"] / max(d["n_stereo_frames"], 1), "{:.1f}")
    row("Rock detection precision / recall",
        lambda d, c: f"{d['stereo_precision']:.3f} / {d['stereo_recall']:.3f}")
    row("Catalog entries (precision / recall)",
        lambda d, c: f"{d['n_catalog']} ({d['catalog_precision']:.3f} / {d['catalog_recall']:.3f})")
    row("Dead reckoning ATE [m]", lambda d, c: runs(c)[DR_KEY]["ate"]["rmse"])
    variants = [run_key(b, r) for b in ("ekf", "isam2") for r in (False, True)]
    for k in variants:
        row(f"{run_label(k)} ATE [m]", lambda d, c, k=k: runs(c)[k]["ate"]["rmse"])
    row("Fixes / attempts", lambda d, c: f"{runs(c)[ref]['fixes']['fixes']} / {runs(c)[ref]['fixes']['attempts']}")
    for k in variants:
        if k.endswith("_reloc"):
            row(f"Fixes accepted by {run_label(k.split('_')[0])}", lambda d, c, k=k: runs(c)[k]["fixes"]["accepted"], "{:d}")
    row("Fix position error median [m]", lambda d, c: runs(c)[ref]["fixes"]["position_error_m"]["median"])
    for k in variants:
        row(f"{run_label(k)} inside 3σ [%]", lambda d, c, k=k: 100 * runs(c)[k]["consistency"]["inside_3sigma"], "{:.1f}")
    for k in variants:
        row(f"{run_label(k)} mean NEES (x,y,yaw)", lambda d, c, k=k: runs(c)[k]["consistency"]["nees_mean"], "{:.2f}")
    row("Image path per frame: render / detect / SGBM [s]",
        lambda d, c: (f"{d['image_render_s_per_frame']:.3f} / {d['image_detect_s_per_frame']:.3f} / "
                      f"{d['image_stereo_s_per_frame']:.3f}") if d.get("image_render_s_per_frame") is not None else "–")
    row("Comparison wall time [s]", lambda d, c: c["wall_s"], "{:.1f}")
    return cols, rows


def markdown(res: dict) -> str:
    """The side-by-side table as Markdown, with what the detection figures count."""
    cols, rows = table_rows(res)
    title = (f"### {res['world']}, seed {res['seed']}: statistical vs image detections "
             f"(stereo frames at {res['stereo_rate_hz']:g} Hz)")
    note = ("Detection precision / recall: statistical = the sensor model's draw over the rocks it deems "
            "visible; image = measured from the renderer's instance image (visible rocks of >= 30 px within "
            "the stereo range). Fixes come from the iSAM2 + reloc reference pass and are replayed to EKF + reloc.")
    lines = [title, "", "| " + " | ".join(cols) + " |", "|---|" + "---:|" * (len(cols) - 1)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    lines += ["", note, ""]
    return "\n".join(lines)

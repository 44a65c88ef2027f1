"""``fgslam bench detect --landmark crater``: the orbital crater detector in the shape of the
reference Table I, with centre and diameter errors, and its timing.

Quality on held-out rendered worlds (the ``eval`` seed stream of :mod:`sim.crater_datasets`,
never used in training): a detection is a true positive when its disc overlaps a true crater's
by IoU >= 0.5 (greedy by score, each crater matched once). Per row of crater sizes: precision and
recall at the model's operating threshold, AP at IoU 0.5 (mAP50) and over IoU 0.50:0.05:0.95
(101-point, as COCO), and over the true positives the centre error |c - c_true| / D_true and the
diameter error |D - D_true| / D_true. Within a size row, true craters of other sizes and
unmatched detections of other sizes count neither way (COCO's area ranges), as do detections on
ignore craters (too small, hidden, or centred outside the image).

The labels are topographic (a bowl deeper than the terrain's relief at its scale); how visible a
crater is in the image also depends on the albedo texture, haze and noise over it. Each true
crater's photometric signal-to-clutter ratio (:func:`sim.crater_datasets.signal_to_clutter`)
is measured on the same images, and the goal's row is given again by it: recall per ratio bin,
and precision and recall where craters under ``SCR_VISIBLE`` count as ignore craters (a reading
of "true crater" by what the image shows; the goal is judged on the topographic labels).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fgslam.bench.detect import (
    IOUS,
    _one_cv_thread,
    _timed,
    average_precision,
    goal_margin_threshold,
)
from reloc.detector.circles import CraterDetections, circle_iou_pairs

GOAL = {"precision": 0.9, "recall": 0.8, "centre_error_d": 0.10, "diameter_error": 0.10, "tile_s": 0.050}
MIN_GOAL_PX = 8.0
SIZE_ROWS = (("all, >= 4 px", 4.0, np.inf), (">= 8 px (goal)", MIN_GOAL_PX, np.inf), ("4-8 px", 4.0, 8.0),
             ("8-16 px", 8.0, 16.0), ("16-32 px", 16.0, 32.0), ("32-64 px", 32.0, 64.0), ("64-128 px", 64.0, 128.0),
             (">= 128 px", 128.0, np.inf))
TILE_PX = 640
SCR_VISIBLE = 2.0  # photometric signal-to-clutter of a crater "an observer would mark" (the second reading)
SCR_BINS = ((0.0, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, np.inf))


def overlaps(dets: CraterDetections, labels) -> tuple[np.ndarray, np.ndarray]:
    """(disc IoU (N, K), near (N, K)) of detections and labelled craters: IoU computed only for
    discs that touch (others 0); ``near``: a fair overlap (IoU >= 0.3) or the detection's centre
    inside the crater at a comparable size, the test for a detection on an ignore crater."""
    from scipy.spatial import cKDTree

    n, k = len(dets), len(labels.diameters_px)
    iou = np.zeros((n, k))
    near = np.zeros((n, k), dtype=bool)
    if n == 0 or k == 0:
        return iou, near
    c, d = dets.centers_px.astype(float), dets.diameters_px.astype(float)
    ct, dt = labels.centres_px.astype(float), labels.diameters_px.astype(float)
    reach = 0.5 * (d.max() + dt.max()) + 1.0
    pairs = cKDTree(c).sparse_distance_matrix(cKDTree(ct), reach, output_type="ndarray")
    i, j = pairs["i"], pairs["j"]
    dist = np.linalg.norm(c[i] - ct[j], axis=1)
    touch = dist < 0.5 * (d[i] + dt[j]) + 1.0
    i, j, dist = i[touch], j[touch], dist[touch]
    v = circle_iou_pairs(c[i], d[i], ct[j], dt[j])
    iou[i, j] = v
    near[i, j] = (v >= 0.3) | ((dist <= 0.5 * dt[j] + 1.0) & (d[i] <= 2.0 * dt[j] + 2.0))
    return iou, near


def match_craters(dets: CraterDetections, labels, iou_thr: float, size_px: tuple[float, float] = (0.0, np.inf),
                  pre: tuple[np.ndarray, np.ndarray] | None = None):
    """Per detection (N,): 1 true positive, 0 false positive, -1 ignored, and the index of its true
    crater in ``labels`` (-1 if none); true craters outside ``size_px`` act as ignore craters.
    ``pre``: :func:`overlaps` of the pair, when already computed."""
    lo, hi = size_px
    d_true = labels.diameters_px
    positive = ~labels.ignore & (d_true >= lo) & (d_true < hi)
    order = np.argsort(-dets.score, kind="stable")
    out = np.zeros(len(dets), dtype=np.int8)
    gt_of = np.full(len(dets), -1, dtype=np.int64)
    if len(dets) == 0:
        return out, gt_of
    iou, near = overlaps(dets, labels) if pre is None else pre
    taken = ~positive.copy()
    on_ignore = (near & ~positive[None]).any(axis=1)
    in_range = (dets.diameters_px >= lo) & (dets.diameters_px < hi)
    has = (np.where(taken[None], 0.0, iou) >= iou_thr).any(axis=1) if len(d_true) else np.zeros(len(dets), bool)
    for k in order:
        if has[k]:
            cand = np.where(taken, -1.0, iou[k])
            j = int(np.argmax(cand))
            if cand[j] >= iou_thr:
                taken[j] = True
                out[k], gt_of[k] = 1, j
                continue
        out[k] = -1 if on_ignore[k] or not in_range[k] else 0
    return out, gt_of


def evaluate_craters(dets: list, labels: list, score_threshold: float, size_px: tuple[float, float]) -> dict:
    """One Table I row for craters of ``size_px`` (see the module doc)."""
    lo, hi = size_px
    n_gt = sum(int(np.sum(~lab.ignore & (lab.diameters_px >= lo) & (lab.diameters_px < hi))) for lab in labels)
    row = {"n_images": len(labels), "n_true": n_gt, "score_threshold": score_threshold}
    aps = []
    pre = [overlaps(det, lab) for det, lab in zip(dets, labels)]
    for thr in IOUS:
        scores, tps, c_err, d_err = [], [], [], []
        for det, lab, p in zip(dets, labels, pre):
            m, j = match_craters(det, lab, float(thr), size_px, p)
            scores.append(det.score[m >= 0])
            tps.append(m[m >= 0])
            if thr == 0.5:
                tp = (m == 1) & (det.score >= score_threshold)
                d_true = lab.diameters_px[j[tp]]
                c_err.append(np.linalg.norm(det.centers_px[tp] - lab.centres_px[j[tp]], axis=1) / d_true)
                d_err.append(np.abs(det.diameters_px[tp] - d_true) / d_true)
        s, t = np.concatenate(scores), np.concatenate(tps)
        aps.append(average_precision(s, t, n_gt) if n_gt else float("nan"))
        if thr == 0.5:
            op = s >= score_threshold
            ce, de = np.concatenate(c_err), np.concatenate(d_err)
            row.update(precision=float(t[op].sum() / max(op.sum(), 1)), recall=float(t[op].sum() / max(n_gt, 1)),
                       n_detections=int(op.sum()), centre_error_d=float(np.mean(ce)) if len(ce) else float("nan"),
                       centre_error_d_median=float(np.median(ce)) if len(ce) else float("nan"),
                       diameter_error=float(np.mean(de)) if len(de) else float("nan"),
                       diameter_error_median=float(np.median(de)) if len(de) else float("nan"))
    row.update(map50=aps[0], map50_95=float(np.mean(aps)))
    return row


def pick_crater_threshold(dets: list, labels: list, goal_precision: float, goal_recall: float, min_px: float) -> float:
    """Score threshold with the widest margin min(precision - goal, recall - goal) for craters of
    ``min_px`` and more (IoU 0.5), over the detections' scores."""
    scores, tps = [], []
    n_gt = sum(int(np.sum(~lab.ignore & (lab.diameters_px >= min_px))) for lab in labels)
    for det, lab in zip(dets, labels):
        m, _ = match_craters(det, lab, 0.5, (min_px, np.inf))
        scores.append(det.score[m >= 0])
        tps.append(m[m >= 0])
    return goal_margin_threshold(np.concatenate(scores), np.concatenate(tps), n_gt, goal_precision, goal_recall)


@dataclass(frozen=True)
class CraterBenchConfig:
    """Held-out images (``image_px`` square), the seed of the eval worlds, timing repetitions."""

    images: int = 12
    image_px: int = 1024
    seed: int = 0
    timing_runs: int = 10
    model: str | None = None


def collect(det, n: int, seed: int, split: str, image_px: int = 1024, step: Callable[[], None] | None = None,
            scr: bool = False):
    """(detections, labels, samples) of ``det`` on ``n`` rendered images of ``split``; ``scr``:
    the samples carry each label's photometric signal-to-clutter ratio."""
    from sim.crater_datasets import CraterSetConfig, crater_samples
    from sim.crater_scene import SceneVariation

    cfg = CraterSetConfig(scene=SceneVariation(size_px=image_px))
    dets, labels, samples = [], [], []
    for s in crater_samples(n, seed, split, cfg, scr=scr):
        dets.append(det.detect(s.image))
        labels.append(s.labels)
        samples.append(s)
        if step is not None:
            step()
    return dets, labels, samples


def run_crater_bench(cfg: CraterBenchConfig, progress: Callable[[str, int], Callable[[], None]] | None = None) -> dict:
    """Quality rows and timings of the crater model; plain data (see :func:`crater_rows`)."""
    from pathlib import Path

    from reloc.detector import CraterDetector, DetectorConfig

    tick = progress or (lambda name, total: (lambda: None))
    op = CraterDetector(cfg.model)
    low = CraterDetector(cfg.model, config=DetectorConfig(score_threshold=0.05))
    t0 = time.perf_counter()
    dets, labels, samples = collect(low, cfg.images, cfg.seed, "eval", cfg.image_px,
                                    tick(f"craters: render + detect {cfg.images} held-out images", cfg.images), scr=True)
    rows = {name: evaluate_craters(dets, labels, op.score_threshold, (lo, hi)) for name, lo, hi in SIZE_ROWS}
    scr = [s.scr for s in samples]
    scr_rows = {f"SCR {lo:g}-{hi:g}": evaluate_craters(dets, scr_labels(labels, scr, lo, hi), op.score_threshold, (MIN_GOAL_PX, np.inf))
                for lo, hi in SCR_BINS}
    visible = evaluate_craters(dets, scr_labels(labels, scr, SCR_VISIBLE, np.inf), op.score_threshold, (MIN_GOAL_PX, np.inf))
    img = samples[0].image
    tile = np.ascontiguousarray(img[:TILE_PX, :TILE_PX])
    x = np.zeros((1, 1, TILE_PX, TILE_PX), np.float32)
    with _one_cv_thread():
        tile_s, tile_cpu_s = _timed(lambda: op.detect(tile), cfg.timing_runs)
        image_s, image_cpu_s = _timed(lambda: op.detect(img), max(cfg.timing_runs // 2, 2))
        net_s, net_cpu_s = _timed(lambda: op.session.run(None, {op.input_name: x}), cfg.timing_runs)
    return {"config": cfg.__dict__.copy(), "rows": rows, "scr_rows": scr_rows, "scr_visible": SCR_VISIBLE,
            "visible_row": visible, "goal": GOAL, "model": str(op.path),
            "model_mb": Path(op.path).stat().st_size / 1e6, "score_threshold": op.score_threshold,
            "n_levels_tile": op.levels(tile.shape), "image_shape": list(img.shape), "bench_s": time.perf_counter() - t0,
            "timing": {"tile_s": tile_s, "tile_cpu_s": tile_cpu_s, "image_s": image_s, "image_cpu_s": image_cpu_s,
                       "network_tile_s": net_s, "network_tile_cpu_s": net_cpu_s}}


def scr_labels(labels: list, scr: list, lo: float, hi: float) -> list:
    """``labels`` with the true craters whose signal-to-clutter ratio is outside [lo, hi) made
    ignore craters (a detection on them counts neither way)."""
    from sim.crater_datasets import CraterLabels

    out = []
    for lab, r in zip(labels, scr):
        inside = (r >= lo) & (r < hi)  # NaN (under 4 px, off the image) is outside
        out.append(CraterLabels(lab.centres_px, lab.diameters_px, lab.ignore | ~inside))
    return out


def crater_scr_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """Craters of 8 px and more by photometric signal-to-clutter ratio: the recall per ratio bin
    (and the share of the true craters in it), then the goal's row with the craters under
    ``scr_visible`` as ignore craters."""
    cols = ["craters >= 8 px", "true", "share", "precision", "recall", "mAP50", "centre err / D", "diameter err %"]
    n_all = sum(r["n_true"] for r in res["scr_rows"].values())
    rows = [[name, str(r["n_true"]), f"{100 * r['n_true'] / max(n_all, 1):.0f} %", "-", f"{r['recall']:.3f}", "-",
             f"{r['centre_error_d']:.3f}", f"{100 * r['diameter_error']:.1f}"] for name, r in res["scr_rows"].items()]
    v = res["visible_row"]
    rows.append([f"SCR >= {res['scr_visible']:g} (the rest ignored)", str(v["n_true"]), f"{100 * v['n_true'] / max(n_all, 1):.0f} %",
                 f"{v['precision']:.3f}", f"{v['recall']:.3f}", f"{v['map50']:.3f}", f"{v['centre_error_d']:.3f}",
                 f"{100 * v['diameter_error']:.1f}"])
    return cols, rows


def crater_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """Table I-style rows per crater size: P, R, mAP50, mAP50-95, centre and diameter errors."""
    cols = ["craters", "images", "true", "precision", "recall", "mAP50", "mAP50-95", "centre err / D (median)",
            "diameter err % (median)", "goal"]
    rows = []
    g = res["goal"]
    for name, r in res["rows"].items():
        goal = "-"
        if name.startswith(">= 8"):
            met = (r["precision"] >= g["precision"] and r["recall"] >= g["recall"]
                   and r["centre_error_d"] <= g["centre_error_d"] and r["diameter_error"] <= g["diameter_error"])
            goal = (f"P >= {g['precision']:.2f}, R >= {g['recall']:.2f}, centre <= {g['centre_error_d']:.2f} D, "
                    f"diameter <= {100 * g['diameter_error']:.0f} % ({'met' if met else 'not met'})")
        rows.append([name, str(r["n_images"]), str(r["n_true"]), f"{r['precision']:.3f}", f"{r['recall']:.3f}",
                     f"{r['map50']:.3f}", f"{r['map50_95']:.3f}",
                     f"{r['centre_error_d']:.3f} ({r['centre_error_d_median']:.3f})",
                     f"{100 * r['diameter_error']:.1f} ({100 * r['diameter_error_median']:.1f})", goal])
    return cols, rows


def crater_timing_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """Timing rows (one onnxruntime thread): a 640 px tile (whole pipeline, against the goal),
    the network alone on it, a whole held-out image; model size."""
    t, g = res["timing"], res["goal"]
    h, w = res["image_shape"][:2]
    cols = ["what", "wall", "CPU", "goal", "model size"]
    met = t["tile_cpu_s"] <= g["tile_s"]
    return cols, [
        [f"detect, {TILE_PX} x {TILE_PX} tile ({res['n_levels_tile']} pyramid levels)", f"{1e3 * t['tile_s']:.1f} ms",
         f"{1e3 * t['tile_cpu_s']:.1f} ms", f"<= {1e3 * g['tile_s']:.0f} ms ({'met' if met else 'not met'})",
         f"{res['model_mb']:.2f} MB"],
        [f"network alone, {TILE_PX} x {TILE_PX}", f"{1e3 * t['network_tile_s']:.1f} ms", f"{1e3 * t['network_tile_cpu_s']:.1f} ms", "-", ""],
        [f"detect, {w} x {h} image", f"{1e3 * t['image_s']:.0f} ms", f"{1e3 * t['image_cpu_s']:.0f} ms",
         f"{1e3 * t['image_cpu_s'] / (h * w / TILE_PX**2):.1f} ms per {TILE_PX}^2", ""],
    ]


def crater_markdown(res: dict) -> str:
    """Both tables as Markdown."""
    out = []
    for title, (cols, rows) in (("Crater detector (held-out rendered worlds)", crater_rows(res)),
                                ("By photometric signal-to-clutter ratio", crater_scr_rows(res)),
                                ("Crater detector timing (one thread)", crater_timing_rows(res))):
        out += [f"### {title}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        out += ["| " + " | ".join(r) + " |" for r in rows]
        out.append("")
    return "\n".join(out)

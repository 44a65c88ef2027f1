"""``fgslam bench detect``: detector quality in the shape of the reference Table I, and timings.

Quality on held-out rendered worlds (the ``eval`` seed stream of :mod:`sim.datasets`, never used
in training): precision and recall at the model's operating score threshold (IoU >= 0.5), AP at
IoU 0.5 (mAP50) and averaged over IoU 0.50:0.05:0.95 (mAP50-95), 101-point interpolated as in
COCO. A detection matched to no true box but overlapping an *ignore* box (a rock too small to
label, see :mod:`sim.datasets`) counts neither way. Timings, all on one thread (onnxruntime,
open3d ray casting and OpenCV each limited to one): inference per image, nadir tile and stereo
pair rendering (checked against the stereo pair goal), SGBM disparity.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial

import numpy as np

from reloc.detector.boxes import iou_matrix

IOUS = np.round(np.arange(0.5, 0.96, 0.05), 2)
REFERENCE = {"nadir": dict(precision=0.440, recall=0.364, map50=0.379), "rover": dict(precision=0.744, recall=0.692, map50=0.737)}
GOALS = {"nadir": dict(precision=0.8, recall=0.7), "rover": dict(precision=0.9, recall=0.85)}
RENDER_STEREO_PAIR_GOAL_S = 0.100  # rover stereo pair, 2 x 640 x 360, one core
TIMED_VIEWS = 3  # held-out images whose rendering is timed


def match_image(boxes: np.ndarray, score: np.ndarray, gt: np.ndarray, ignore: np.ndarray, iou_thr: float) -> np.ndarray:
    """Per detection (N,): 1 true positive, 0 false positive, -1 ignored; greedy by score."""
    order = np.argsort(-score, kind="stable")
    out = np.zeros(len(score), dtype=np.int8)
    iou = iou_matrix(boxes, gt) if len(gt) else np.zeros((len(boxes), 0))
    taken = np.zeros(len(gt), dtype=bool)
    if len(ignore):
        b = np.reshape(boxes, (-1, 4))
        g = np.reshape(ignore, (-1, 4))
        iw = np.clip(np.minimum(b[:, None, 2], g[None, :, 2]) - np.maximum(b[:, None, 0], g[None, :, 0]), 0, None)
        ih = np.clip(np.minimum(b[:, None, 3], g[None, :, 3]) - np.maximum(b[:, None, 1], g[None, :, 1]), 0, None)
        area = np.maximum((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]), 1e-9)
        on_ignore = (iw * ih / area[:, None]).max(axis=1) >= 0.3
    else:
        on_ignore = np.zeros(len(score), dtype=bool)
    for k in order:
        if len(gt):
            cand = np.where(taken, -1.0, iou[k])
            j = int(np.argmax(cand))
            if cand[j] >= iou_thr:
                taken[j] = True
                out[k] = 1
                continue
        out[k] = -1 if on_ignore[k] else 0
    return out


def average_precision(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> float:
    """COCO 101-point interpolated AP of detections with ``scores`` (N,) and ``tp`` (N,) in {0, 1}."""
    if n_gt == 0:
        return float("nan")
    if len(scores) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    t = tp[order].astype(float)
    ctp, cfp = np.cumsum(t), np.cumsum(1 - t)
    rec = ctp / n_gt
    prec = ctp / np.maximum(ctp + cfp, 1e-12)
    prec = np.maximum.accumulate(prec[::-1])[::-1] if len(prec) else prec
    grid = np.linspace(0, 1, 101)
    idx = np.searchsorted(rec, grid, side="left")
    return float(np.mean(np.where(idx < len(prec), prec[np.minimum(idx, len(prec) - 1)], 0.0)))


@dataclass
class Quality:
    precision: float
    recall: float
    map50: float
    map50_95: float
    n_images: int
    n_true: int
    n_detections: int
    score_threshold: float


def evaluate(dets: list, labels: list, score_threshold: float) -> Quality:
    """Quality of per-image detections (``Detections``, run at a low threshold) against per-image
    ``BoxLabels``; precision/recall at ``score_threshold``, APs over the whole score range."""
    n_gt = sum(int(np.sum(~lab.ignore)) for lab in labels)
    aps = []
    p = r = 0.0
    n_op = 0
    for thr in IOUS:
        scores, tps = [], []
        for d, lab in zip(dets, labels):
            m = match_image(d.boxes_xyxy, d.score, lab.boxes_xyxy[~lab.ignore], lab.boxes_xyxy[lab.ignore], thr)
            scores.append(d.score[m >= 0])
            tps.append(m[m >= 0])
        s, t = np.concatenate(scores), np.concatenate(tps)
        aps.append(average_precision(s, t, n_gt))
        if thr == 0.5:
            op = s >= score_threshold
            n_op = int(op.sum())
            p = float(t[op].sum() / max(n_op, 1))
            r = float(t[op].sum() / max(n_gt, 1))
    return Quality(p, r, aps[0], float(np.mean(aps)), len(labels), n_gt, n_op, score_threshold)


def pick_threshold(dets: list, labels: list, target_precision: float) -> float:
    """Score threshold with the highest recall at precision >= ``target_precision`` (IoU 0.5);
    the F1-best threshold when no threshold reaches that precision."""
    n_gt = sum(int(np.sum(~lab.ignore)) for lab in labels)
    scores, tps = [], []
    for d, lab in zip(dets, labels):
        m = match_image(d.boxes_xyxy, d.score, lab.boxes_xyxy[~lab.ignore], lab.boxes_xyxy[lab.ignore], 0.5)
        scores.append(d.score[m >= 0])
        tps.append(m[m >= 0])
    s, t = np.concatenate(scores), np.concatenate(tps)
    order = np.argsort(-s, kind="stable")
    s, t = s[order], t[order].astype(float)
    ctp = np.cumsum(t)
    prec = ctp / np.arange(1, len(t) + 1)
    rec = ctp / max(n_gt, 1)
    if len(s) == 0:
        return 0.3
    ok = np.flatnonzero(prec >= target_precision)
    k = ok[np.argmax(rec[ok])] if len(ok) else int(np.argmax(2 * prec * rec / np.maximum(prec + rec, 1e-12)))
    return float(max(s[k], 0.05))


def pick_threshold_for_goal(dets: list, labels: list, goal_precision: float, goal_recall: float) -> float:
    """Score threshold with the widest margin to both goals (IoU 0.5): the one maximising
    min(precision - ``goal_precision``, recall - ``goal_recall``) over the detections' scores, so
    that the operating point keeps its distance from both goals on unseen worlds."""
    scores, tps = [], []
    n_gt = sum(int(np.sum(~lab.ignore)) for lab in labels)
    for d, lab in zip(dets, labels):
        m = match_image(d.boxes_xyxy, d.score, lab.boxes_xyxy[~lab.ignore], lab.boxes_xyxy[lab.ignore], 0.5)
        scores.append(d.score[m >= 0])
        tps.append(m[m >= 0])
    return goal_margin_threshold(np.concatenate(scores), np.concatenate(tps), n_gt, goal_precision, goal_recall)


def goal_margin_threshold(s: np.ndarray, t: np.ndarray, n_gt: int, goal_precision: float, goal_recall: float) -> float:
    """The score threshold maximising min(precision - goal, recall - goal) over counted detections
    with scores ``s`` (N,) and true-positive flags ``t`` (N,) against ``n_gt`` true objects."""
    if len(s) == 0:
        return 0.3
    order = np.argsort(-s, kind="stable")
    s, t = s[order], t[order].astype(float)
    ctp = np.cumsum(t)
    margin = np.minimum(ctp / np.arange(1, len(t) + 1) - goal_precision, ctp / max(n_gt, 1) - goal_recall)
    last = np.r_[s[1:] != s[:-1], True]  # a threshold keeps every detection of equal score
    k = int(np.flatnonzero(last)[np.argmax(margin[last])])
    return float(max(s[k], 0.05))


@dataclass(frozen=True)
class DetectBenchConfig:
    """Held-out images per model, the seed of the eval worlds, timing repetitions."""

    nadir_images: int = 24
    rover_images: int = 40
    seed: int = 0
    timing_runs: int = 20
    nadir_model: str | None = None
    rover_model: str | None = None


def _timed(fn: Callable, runs: int) -> tuple[float, float]:
    """Median wall time and median process CPU time (all threads; on one core the two agree,
    and on a machine shared with other jobs the CPU time is the steadier figure) of ``fn()``, s."""
    wall, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


@contextlib.contextmanager
def _one_cv_thread() -> Iterator[None]:
    """OpenCV on one thread inside the block (the renderer's texture lookup, SGBM)."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _render_timings(kind: str, samples: list, runs: int) -> dict:
    """Median over ``samples`` of the median time of rendering each one again on one thread, s
    (wall and process CPU), and for rover views SGBM on the first pair."""
    from sim.render import Renderer

    per_view: list[tuple[float, float]] = []
    out: dict = {}
    with _one_cv_thread():
        for s in samples:
            r = Renderer(s.world, nthreads=1)
            render = (partial(r.nadir, s.nadir.gsd_m, extent=s.nadir.extent) if kind == "nadir"
                      else partial(r.stereo, s.stereo.T_world_left, s.stereo.camera, s.stereo.baseline_m))
            render()  # builds the world's ray caster once
            per_view.append(_timed(render, runs))
        key = "render_tile" if kind == "nadir" else "render_stereo_pair"
        out[f"{key}_s"] = float(np.median([w for w, _ in per_view]))
        out[f"{key}_cpu_s"] = float(np.median([c for _, c in per_view]))
        out[f"{key}_views"] = len(per_view)
        if kind == "rover":
            from reloc.stereo import sgbm_disparity

            sr = samples[0].stereo
            out["sgbm_s"], out["sgbm_cpu_s"] = _timed(lambda: sgbm_disparity(sr.left, sr.right), max(runs // 2, 2))
            out["render_stereo_pair_goal_s"] = RENDER_STEREO_PAIR_GOAL_S
    return out


def run_detect_bench(cfg: DetectBenchConfig, progress: Callable[[str, int], Callable[[], None]] | None = None) -> dict:
    """Quality and timing of both models; returns plain data (see :func:`result_rows`)."""
    from pathlib import Path

    from reloc.detector import DetectorConfig, RockDetector
    from sim.datasets import nadir_samples, rover_samples

    tick = progress or (lambda name, total: (lambda: None))
    res: dict = {"config": cfg.__dict__.copy(), "models": {}}
    for kind, n, gen, path in (("nadir", cfg.nadir_images, nadir_samples, cfg.nadir_model),
                               ("rover", cfg.rover_images, rover_samples, cfg.rover_model)):
        op = RockDetector(path, kind=kind)
        low = RockDetector(path, kind=kind, config=DetectorConfig(score_threshold=0.05))
        step = tick(f"{kind}: render + detect {n} held-out images", n)
        dets, labels, render_s, samples = [], [], [], []
        t0 = time.perf_counter()
        for s in gen(n, cfg.seed, "eval"):
            render_s.append(time.perf_counter() - t0)
            dets.append(low.detect(s.image))
            labels.append(s.labels)
            if len(samples) < TIMED_VIEWS:
                samples.append(s)
            step()
            t0 = time.perf_counter()
        q = evaluate(dets, labels, op.score_threshold)
        img = samples[0].image
        infer_s, infer_cpu_s = _timed(lambda: op.detect(img), cfg.timing_runs)
        x = np.zeros((1, op.channels, op.input_size_wh[1], op.input_size_wh[0]), np.float32)
        net_s, _ = _timed(lambda: op.session.run(None, {op.input_name: x}), cfg.timing_runs)
        entry = {"quality": q.__dict__, "infer_image_s": infer_s, "infer_image_cpu_s": infer_cpu_s, "infer_network_s": net_s,
                 "image_shape": list(img.shape), "input_size_wh": list(op.input_size_wh),
                 "model": str(op.path), "model_mb": Path(op.path).stat().st_size / 1e6,
                 "reference": REFERENCE[kind], "goal": GOALS[kind]}
        entry.update(_render_timings(kind, samples, max(cfg.timing_runs // (4 if kind == "nadir" else 2), 2)))
        res["models"][kind] = entry
    return res


def result_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """Table I-style rows: model, P, R, mAP50, mAP50-95 (ours and the reference)."""
    cols = ["model", "images", "true boxes", "precision", "recall", "mAP50", "mAP50-95", "threshold", "reference P / R / mAP50", "goal P / R"]
    rows = []
    for kind, e in res["models"].items():
        q, ref, goal = e["quality"], e["reference"], e["goal"]
        rows.append([kind, str(q["n_images"]), str(q["n_true"]), f"{q['precision']:.3f}", f"{q['recall']:.3f}",
                     f"{q['map50']:.3f}", f"{q['map50_95']:.3f}", f"{q['score_threshold']:.2f}",
                     f"{ref['precision']:.3f} / {ref['recall']:.3f} / {ref['map50']:.3f}",
                     f"{goal['precision']:.2f} / {goal['recall']:.2f}"])
    return cols, rows


def timing_rows(res: dict) -> tuple[list[str], list[list[str]]]:
    """Timing rows: inference (image and network alone), rendering (the stereo pair against its
    goal, judged on CPU time: one thread, so the work of one core even on a shared machine),
    model size."""
    cols = ["model", "image", "network input", "inference / image (CPU)", "network alone", "render wall (CPU)",
            "render goal", "model size"]
    rows = []

    def ms(e: dict, key: str) -> str:
        cpu = e.get(key[:-2] + "_cpu_s")
        return f"{1e3 * e[key]:.0f} ms" + ("" if cpu is None else f" ({1e3 * cpu:.0f} ms)")

    for kind, e in res["models"].items():
        render = (f"tile {ms(e, 'render_tile_s')}" if "render_tile_s" in e
                  else f"stereo pair {ms(e, 'render_stereo_pair_s')}, SGBM {ms(e, 'sgbm_s')}")
        goal = "-"
        if "render_stereo_pair_goal_s" in e:
            met = e["render_stereo_pair_cpu_s"] <= e["render_stereo_pair_goal_s"]
            goal = f"pair <= {1e3 * e['render_stereo_pair_goal_s']:.0f} ms ({'met' if met else 'not met'})"
        rows.append([kind, "x".join(str(v) for v in e["image_shape"]), "x".join(str(v) for v in e["input_size_wh"]),
                     f"{1e3 * e['infer_image_s']:.1f} ms ({1e3 * e.get('infer_image_cpu_s', float('nan')):.1f} ms)",
                     f"{1e3 * e['infer_network_s']:.1f} ms", render, goal, f"{e['model_mb']:.2f} MB"])
    return cols, rows


def markdown(res: dict) -> str:
    """Both tables as Markdown."""
    out = []
    for title, (cols, rows) in (("Detector quality (held-out rendered worlds)", result_rows(res)), ("Timings (one thread)", timing_rows(res))):
        out += [f"### {title}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        out += ["| " + " | ".join(r) + " |" for r in rows]
        out.append("")
    return "\n".join(out)

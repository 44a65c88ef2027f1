"""Train the orbital crater detector on rendered cratered scenes and export it to ONNX.

    python -m fgslam.train --kind crater --images 320 --minutes 40 --out src/reloc/models/craters_orbital.onnx

Data: clean scenes of :mod:`sim.crater_scene` (rendered once, cached to ``--cache``), and per
training crop a fresh camera (:func:`sim.crater_datasets.orbital_sensor`) and scale: a crop
covers ``CROP_PX`` x s scene pixels, s log-uniform in ``SCALE``, averaged down to ``CROP_PX``,
with the camera applied before the reduction (how a pyramid level of a sharp image looks) or
after it (a coarser camera). Then the runtime's normalisation (:func:`reloc.detector.image.
normalised_grey`), contrast and brightness jitter, flips and quarter turns.

Craters from 3.5 to 32 px across (in the crop) are the targets; smaller, larger or hidden ones
are ignored around their centres. With ``--min-scr R`` (scenes rendered with their ground
without craters), a crater whose photometric signal-to-clutter ratio in the crop's own camera
image is under R (:func:`sim.crater_datasets.signal_to_clutter`: what albedo texture, haze and
noise hide) is ignored too, so the network is not taught to fire where the image shows nothing. The runtime covers 4-200 px and more with an image pyramid,
keeping at each level the craters of a band inside that range (:mod:`reloc.detector.craters`).
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

ARCH = {"widths": (12, 24, 48, 96, 128), "out_stride": 2, "fine_width": 12, "n_out": 4}
CROP_PX = 192
SCALE = (1.0, 2.8)
# training scenes carry up to 3 x the model's density of craters above 24 px (rare, and the
# ones the coarse pyramid levels see); validation and evaluation scenes keep the model's
TRAIN_SCENES = {"large_crater_boost": (1.0, 3.0)}
TRAIN_DIAMETER_PX = (3.5, 32.0)  # targets in a crop; outside this range a crater is ignored
SIGMA_PER_DIAMETER = 0.1  # heatmap Gaussian sigma / crater diameter
SIZE_WEIGHT = 1.0  # L1 weight of log diameter (relative to the offsets')
INPUT_SIZE_WH = (640, 640)  # the tile the runtime cuts large images into
VAL_IMAGE_PX = 512  # side of the validation images the score threshold is chosen on


def _render_one(args: tuple[int, str, int, bool]) -> dict:
    from sim.crater_datasets import scene_rng
    from sim.crater_scene import SceneVariation, render_crater_scene

    seed, split, k, ground = args
    s = render_crater_scene(SceneVariation(**TRAIN_SCENES), scene_rng(seed, split, k), without_craters=ground)
    out = {"grey": np.rint(s.grey * 65535).astype(np.uint16), "centres": s.centres_px.astype(np.float32),
           "diameters": s.diameters_px.astype(np.float32), "visible": s.visible}
    if ground:
        out["ground"] = np.rint(s.grey_without_craters * 65535).astype(np.uint16)
    return out


def render_scenes(n: int, seed: int, split: str = "train", workers: int = 1, ground: bool = False) -> list[dict]:
    """``n`` clean scenes of ``split`` as dicts (grey uint16, centres, diameters, visible, and
    with ``ground`` the same ground without craters, uint16); the same list whatever
    ``workers`` (each scene has its own seed)."""
    jobs = [(seed, split, k, ground) for k in range(n)]
    if workers <= 1:
        return [_render_one(j) for j in jobs]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(_render_one, jobs, chunksize=4))


def save_scenes(path: Path, scenes: list[dict]) -> None:
    """Cache scenes as one .npz."""
    np.savez_compressed(path, n=len(scenes), **{f"{key}{k}": v for k, s in enumerate(scenes) for key, v in s.items()})


def load_scenes(path: Path) -> list[dict]:
    """Scenes written by :func:`save_scenes`."""
    z = np.load(path)
    keys = ("grey", "centres", "diameters", "visible") + (("ground",) if "ground0" in z.files else ())
    return [{key: z[f"{key}{k}"] for key in keys} for k in range(int(z["n"]))]


def crop_sample(scene: dict, rng: np.random.Generator, crop: int = CROP_PX, min_scr: float = 0.0):
    """One augmented training crop of ``scene``: (x (crop, crop) float32 normalised, positive
    centres (P, 2) and diameters (P,), ignore boxes (Q, 4)), pixels of the crop. ``min_scr`` > 0:
    targets whose signal-to-clutter ratio in this crop's camera image is lower are ignored
    (needs the scene's ``ground``; the crop is the same as without it)."""
    import copy

    import cv2

    from reloc.detector.image import normalised_grey
    from sim.crater_datasets import orbital_sensor, signal_to_clutter

    grey = scene["grey"]
    if min_scr > 0 and "ground" not in scene:
        raise ValueError("crop_sample: min_scr needs scenes rendered with their ground (render_scenes(..., ground=True))")
    size = min(grey.shape)
    s = float(np.exp(rng.uniform(*np.log(SCALE))))
    win = min(round(crop * s), size)
    s = win / crop
    x0, y0 = int(rng.integers(0, grey.shape[1] - win + 1)), int(rng.integers(0, grey.shape[0] - win + 1))
    gamma = np.float32(np.exp(rng.uniform(np.log(0.7), np.log(1.4))))  # the stretch of a product

    def window(a: np.ndarray) -> np.ndarray:
        return (a[y0:y0 + win, x0:x0 + win].astype(np.float32) / 65535.0) ** gamma

    g = window(grey)
    before = rng.random() < 0.5  # the camera before the reduction (its pixels: the window's) or after
    if not before and win != crop:
        g = cv2.resize(g, (crop, crop), interpolation=cv2.INTER_AREA)
    camera = copy.deepcopy(rng) if min_scr > 0 else None
    raw = orbital_sensor(g, rng)
    x, _ = normalised_grey(raw)
    if before and win != crop:
        x = cv2.resize(x, (crop, crop), interpolation=cv2.INTER_AREA)
    x = (x - 0.5) * np.float32(np.exp(rng.uniform(-0.25, 0.25))) + np.float32(0.5 + rng.uniform(-0.08, 0.08))
    c = (scene["centres"] - np.array([x0, y0], np.float32)) / s
    d = scene["diameters"] / s
    r = 0.5 * d
    reaches = (c[:, 0] + r > 0) & (c[:, 0] - r < crop) & (c[:, 1] + r > 0) & (c[:, 1] - r < crop) & (d >= 2.0)
    inside = (c[:, 0] >= 0) & (c[:, 0] < crop) & (c[:, 1] >= 0) & (c[:, 1] < crop)
    pos = inside & scene["visible"] & (d >= TRAIN_DIAMETER_PX[0]) & (d <= TRAIN_DIAMETER_PX[1])
    if min_scr > 0 and pos.any():
        g0 = window(scene["ground"])
        if not before and win != crop:
            g0 = cv2.resize(g0, (crop, crop), interpolation=cv2.INTER_AREA)
        k = 1.0 if not before else s  # crop pixels -> pixels of the camera image
        ratio = signal_to_clutter(raw, orbital_sensor(g0, camera), c[pos] * k, d[pos] * k, min_px=0.0)
        pos[np.flatnonzero(pos)[~(ratio >= min_scr)]] = False
    ign = reaches & ~pos & inside
    for _ in range(int(rng.integers(0, 4))):  # quarter turns (counter-clockwise)
        x = np.rot90(x)
        c = np.column_stack([c[:, 1], crop - c[:, 0]])
    if rng.random() < 0.5:
        x = x[:, ::-1]
        c = np.column_stack([crop - c[:, 0], c[:, 1]])
    half = np.maximum(0.25 * d[ign], 3.0)
    boxes = np.column_stack([c[ign, 0] - half, c[ign, 1] - half, c[ign, 0] + half, c[ign, 1] + half])
    return np.ascontiguousarray(x, dtype=np.float32), c[pos], d[pos], boxes


def train_craters(scenes: list[dict], *, iters: int, batch: int, crop: int, lr: float, seed: int, device: str,
                  budget_s: float | None = None, init: Path | None = None, arch: dict | None = None,
                  min_scr: float = 0.0):
    """Train the crater network (``ARCH`` unless ``arch``; ``init`` resumes saved weights) on crops
    of ``scenes``; returns (net, loss history) as :func:`fgslam.train.detector.fit`. ``min_scr``:
    see :func:`crop_sample`."""
    import torch

    from fgslam.train.detector import fit, load_onnx_weights, load_weights, stack_targets
    from fgslam.train.model import DetectorNet
    from fgslam.train.targets import centre_targets

    torch.manual_seed(seed)
    rng = np.random.default_rng([seed, 41])
    if init is None:
        net = DetectorNet(**(arch or ARCH))
    else:
        net = load_onnx_weights(init) if Path(init).suffix == ".onnx" else load_weights(init)
    stride = net.out_stride

    def next_batch():
        xs, tg = [], []
        for _ in range(batch):
            x, c, d, boxes = crop_sample(scenes[int(rng.integers(len(scenes)))], rng, crop, min_scr)
            xs.append(x)
            tg.append(centre_targets(c, d[:, None], boxes, crop, crop, stride, sigma_per_size=SIGMA_PER_DIAMETER))
        return np.stack(xs)[:, None], stack_targets(tg)

    return fit(net, next_batch, iters=iters, lr=lr, device=device, budget_s=budget_s, size_weight=SIZE_WEIGHT,
               tag="crater")


def run(args) -> int:
    """``python -m fgslam.train --kind crater``: render (or read the cache), train, export."""
    import json

    import torch

    from fgslam.train.detector import export_onnx, save_weights

    torch.set_num_threads(args.threads)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    t0 = time.perf_counter()
    min_scr = args.min_scr
    if args.cache is not None and args.cache.is_file():
        scenes = load_scenes(args.cache)
        if min_scr > 0 and "ground" not in scenes[0]:
            raise SystemExit(f"--min-scr needs a cache rendered with it (the ground without craters); {args.cache} has none")
    else:
        scenes = render_scenes(args.images, args.seed, "train", workers=args.workers, ground=min_scr > 0)
        if args.cache is not None:
            save_scenes(args.cache, scenes)
    t_render = time.perf_counter() - t0
    log.info("%d crater scenes, %d craters >= 4 px, rendered in %.0f s", len(scenes),
             sum(int(np.sum(s["diameters"] >= 4)) for s in scenes), t_render)
    if args.render_only:
        return 0
    t1 = time.perf_counter()
    net, hist = train_craters(scenes, iters=args.iters, batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed,
                              device=device, budget_s=None if args.minutes is None else 60.0 * args.minutes,
                              init=args.init, min_scr=min_scr)
    t_train = time.perf_counter() - t1
    info = {"images": len(scenes), "data": "sim.crater_datasets train split", "iters": len(hist), "arch": net.arch,
            "lr": args.lr, "batch": args.batch, "crop": args.crop, "scale": list(SCALE), "seed": args.seed,
            "device": device, "threads": args.threads, "data_s": round(t_render, 1), "train_s": round(t_train, 1),
            "final_loss": round(float(np.mean(hist[-50:])), 4), "command": getattr(args, "command", ""),
            "init": None if args.init is None else str(args.init), "min_scr": min_scr}
    if args.weights is not None:
        save_weights(net, args.weights)
    export_onnx(net, "crater", args.out, info, input_size_wh=INPUT_SIZE_WH,
                extra_meta={"diameter_range_px": f"{TRAIN_DIAMETER_PX[0]},{TRAIN_DIAMETER_PX[1]}",
                            "normalisation": "p1-p99 to 0.1-0.9"})
    log.info("wrote %s (%.2f MB): %s", args.out, args.out.stat().st_size / 1e6, json.dumps(info))
    return 0


def calibrate_crater_threshold(path: Path, n: int, seed: int) -> float:
    """Pick the operating score threshold of the crater model at ``path`` on ``n`` rendered
    ``val`` images of ``VAL_IMAGE_PX`` (the widest margin to the precision and recall goals for craters of 8 px and
    more, ``fgslam.bench.detect_craters.GOAL``) and store it in its metadata."""
    from fgslam.bench.detect_craters import GOAL, MIN_GOAL_PX, collect, pick_crater_threshold
    from fgslam.train.detector import set_metadata
    from reloc.detector import CraterDetector, DetectorConfig

    det = CraterDetector(path, config=DetectorConfig(score_threshold=0.05))
    dets, labels, _ = collect(det, n, seed, "val", VAL_IMAGE_PX)
    thr = pick_crater_threshold(dets, labels, GOAL["precision"], GOAL["recall"], MIN_GOAL_PX)
    set_metadata(path, score_threshold=f"{thr:.4f}")
    return thr

"""Train a rock detector on rendered images of procedurally varied worlds and export it to ONNX.

    python -m fgslam.train --kind rover --images 640 --minutes 45 --out src/reloc/models/rocks_rover.onnx

The data set is rendered first (``sim.datasets``; cached to ``--cache`` when given), then the
network of :mod:`fgslam.train.model` (architecture per kind in ``ARCH``) is trained on random
crops with flips, rotations (nadir) and photometric jitter, with AdamW and a cosine learning rate
over ``--iters`` steps or over a ``--minutes`` wall-clock budget. Runs on CUDA when available,
else on CPU with ``--threads`` threads. The exported graph takes (1, 1, H, W) float in [0, 1] with
dynamic H, W (multiples of 16) and returns (1, 5, H/s, W/s); with ``--flip-tta`` it also runs the
mirrored image and averages the two outputs. Its metadata names the layout, the stride, the input
size the runtime letterboxes to, and the operating score threshold chosen on the ``val`` split.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

INPUT_SIZE = {"nadir": (640, 640), "rover": (640, 368)}  # (W, H) the runtime letterboxes to
OUT_STRIDE = {"nadir": 2, "rover": 2}  # nadir rocks are a few pixels across, rover boxes from 5 px
ARCH = {"nadir": {"widths": (8, 24, 48, 96), "out_stride": 2, "fine_width": 12},
        "rover": {"widths": (12, 32, 64, 128), "out_stride": 2, "fine_width": 16}}
FLIP_TTA = {"nadir": False, "rover": False}  # mirror TTA: +0.3 pt mAP50 for 2x inference (rover, val)


def render_set(kind: str, n: int, seed: int, split: str = "train"):
    """Rendered (images list of (H, W) uint8, positive boxes list of (P, 4), ignore boxes list)."""
    from sim.datasets import nadir_samples, rover_samples

    gen = nadir_samples(n, seed, split) if kind == "nadir" else rover_samples(n, seed, split)
    images, pos, ign = [], [], []
    for s in gen:
        images.append(s.image)
        pos.append(s.labels.boxes_xyxy[~s.labels.ignore])
        ign.append(s.labels.boxes_xyxy[s.labels.ignore])
    return images, pos, ign


def save_set(path: Path, images, pos, ign) -> None:
    """Cache a rendered set as one .npz."""
    np.savez_compressed(path, n=len(images), **{f"img{k}": im for k, im in enumerate(images)},
                        **{f"pos{k}": p for k, p in enumerate(pos)}, **{f"ign{k}": g for k, g in enumerate(ign)})


def load_set(path: Path):
    """Read a set written by :func:`save_set`."""
    z = np.load(path)
    n = int(z["n"])
    return [z[f"img{k}"] for k in range(n)], [z[f"pos{k}"] for k in range(n)], [z[f"ign{k}"] for k in range(n)]


def _crop(img, pos, ign, crop: int, rng: np.random.Generator, rotate: bool):
    """A random crop x crop window with augmentation; boxes cut to less than half become ignore."""
    H, W = img.shape
    if H < crop or W < crop:
        pad = np.zeros((max(H, crop), max(W, crop)), np.uint8)
        pad[:H, :W] = img
        img, H, W = pad, max(H, crop), max(W, crop)
    y0, x0 = int(rng.integers(0, H - crop + 1)), int(rng.integers(0, W - crop + 1))
    im = img[y0:y0 + crop, x0:x0 + crop].astype(np.float32)
    off = np.array([x0, y0, x0, y0], np.float32)

    def clip(b):
        b = np.reshape(b, (-1, 4)) - off
        c = np.clip(b, 0, crop)
        area = np.maximum(b[:, 2] - b[:, 0], 0) * np.maximum(b[:, 3] - b[:, 1], 0)
        carea = np.maximum(c[:, 2] - c[:, 0], 0) * np.maximum(c[:, 3] - c[:, 1], 0)
        return c, carea / np.maximum(area, 1e-6)

    p, pf = clip(pos)
    g, gf = clip(ign)
    keep = pf >= 0.5
    ign_all = np.vstack([g[gf > 0], p[(pf > 0) & ~keep]])
    p = p[keep]
    if rng.random() < 0.5:  # horizontal flip
        im = im[:, ::-1]
        p = np.column_stack([crop - p[:, 2], p[:, 1], crop - p[:, 0], p[:, 3]])
        ign_all = np.column_stack([crop - ign_all[:, 2], ign_all[:, 1], crop - ign_all[:, 0], ign_all[:, 3]])
    if rotate:
        for _ in range(int(rng.integers(0, 4))):  # 90-degree turns (counter-clockwise)
            im = np.rot90(im)
            p = np.column_stack([p[:, 1], crop - p[:, 2], p[:, 3], crop - p[:, 0]])
            ign_all = np.column_stack([ign_all[:, 1], crop - ign_all[:, 2], ign_all[:, 3], crop - ign_all[:, 0]])
    gain, bias, gamma = rng.uniform(0.7, 1.3), rng.uniform(-25, 25), rng.uniform(0.8, 1.25)
    im = 255.0 * (np.clip(im * gain + bias, 0, 255) / 255.0) ** gamma
    im = im + rng.uniform(0, 4) * rng.standard_normal(im.shape)
    return np.clip(im, 0, 255) / 255.0, p, ign_all


def load_weights(path: Path):
    """A :class:`RockNet` from weights saved by :func:`save_weights` (or a bare state dict of the
    default architecture with the stride of its keys)."""
    import torch

    from fgslam.train.model import RockNet

    obj = torch.load(path, map_location="cpu")
    if "arch" in obj and "state" in obj:
        arch, state = obj["arch"], obj["state"]
    else:
        arch, state = {"out_stride": 2 if "fuse1.0.weight" in obj else 4}, obj
    net = RockNet(**arch)
    net.load_state_dict(state)
    if obj.get("frozen_bn", False):
        net.frozen_bn = True
    return net


def load_onnx_weights(path: Path):
    """A :class:`DetectorNet` holding the weights of an exported model (``path``, .onnx), for
    fine-tuning a shipped model whose .pt is not at hand. The exporter folds each batch norm into
    the convolution before it, so the net gets the folded weights and batch norms that are the
    identity (mean 0, variance 1 - eps, scale 1, shift the folded bias) and frozen
    (``net.frozen_bn``: :func:`fit` keeps them in eval mode; their scale and shift still train);
    its output equals the model's. The architecture comes from the model's ``train_info``."""
    import onnx
    import torch
    from onnx import numpy_helper

    from fgslam.train.model import DetectorNet

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    try:
        arch = json.loads(meta["train_info"])["arch"]
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: no architecture in the model's train_info metadata ({exc})") from exc
    arch = {k: tuple(v) if isinstance(v, list) else v for k, v in arch.items()}
    net = DetectorNet(**arch)
    inits = {i.name: np.array(numpy_helper.to_array(i)) for i in model.graph.initializer}
    modules = dict(net.named_modules())
    seen = set()
    for node in model.graph.node:
        if node.op_type != "Conv":
            continue
        parts = node.name.strip("/").split("/")  # /net/s2/s2.1/s2.1.0/Conv -> module s2.1.0
        if len(parts) < 3 or parts[0] != "net" or parts[-2] not in modules:
            raise ValueError(f"{path}: convolution {node.name!r} has no module in {arch}")
        name = parts[-2]
        conv = modules[name]
        w, b = inits[node.input[1]], inits[node.input[2]]
        if tuple(conv.weight.shape) != w.shape:
            raise ValueError(f"{path}: {name} weight {w.shape} against {tuple(conv.weight.shape)}")
        parent, _, idx = name.rpartition(".")
        bn = modules.get(f"{parent}.{int(idx) + 1}") if idx.isdigit() else None
        with torch.no_grad():
            conv.weight.copy_(torch.from_numpy(w))
            if isinstance(bn, torch.nn.BatchNorm2d):
                bn.weight.fill_(1.0)
                bn.bias.copy_(torch.from_numpy(b))
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
            else:
                conv.bias.copy_(torch.from_numpy(b))
        seen.add(name)
    convs = {n for n, m in modules.items() if isinstance(m, torch.nn.Conv2d)}
    if seen != convs:
        raise ValueError(f"{path}: convolutions without weights in the model: {sorted(convs - seen)}")
    net.frozen_bn = True
    return net


def save_weights(net, path: Path) -> None:
    """Save ``net``'s architecture and weights (.pt) for :func:`load_weights`."""
    import torch

    torch.save({"arch": dict(net.arch), "state": net.state_dict(), "frozen_bn": bool(getattr(net, "frozen_bn", False))},
               path)


def fit(net, next_batch, *, iters: int, lr: float, device: str, budget_s: float | None = None,
        log_every: int = 50, size_weight: float = 0.5, tag: str = ""):
    """Optimise ``net`` with AdamW on batches ``next_batch()`` -> (x (B, 1, H, W) float32, targets
    of :func:`fgslam.train.targets.centre_targets` stacked per key) for ``iters`` steps, or for
    ``budget_s`` seconds (learning rate on the elapsed share of it: a shared machine's step time
    drifts); linear warm-up, then cosine to 1 %. Returns (net in eval mode on CPU, loss history)."""
    import torch

    from fgslam.train.targets import detector_loss

    net = net.to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    warm = max(iters // 20, 1) if budget_s is None else 20

    def lr_factor(k: int, progress: float) -> float:
        return min((k + 1) / warm, 0.5 * (1 + np.cos(np.pi * min(progress, 1.0)))) + 0.01

    history = []
    t0 = time.perf_counter()
    net.train()
    if getattr(net, "frozen_bn", False):  # folded weights (load_onnx_weights): statistics stay
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.eval()
    it = 0
    while (it < iters) if budget_s is None else (time.perf_counter() - t0 < budget_s):
        progress = it / iters if budget_s is None else (time.perf_counter() - t0) / budget_s
        for group in opt.param_groups:
            group["lr"] = lr * lr_factor(it, progress)
        xs, tg = next_batch()
        x = torch.from_numpy(xs).to(device)
        t = {key: torch.from_numpy(v).to(device) for key, v in tg.items()}
        loss, parts = detector_loss(net(x), t["heat"], t["weight"], t["reg"], t["mask"], size_weight)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        history.append(float(loss.detach()))
        if (it + 1) % log_every == 0 or it == 0:
            log.info("%s iter %d loss %.3f (heat %.3f off %.3f size %.3f) lr %.2g, %.0f s", tag, it + 1, history[-1],
                     parts["heat"], parts["off"], parts["size"], opt.param_groups[0]["lr"], time.perf_counter() - t0)
        it += 1
    return net.cpu().eval(), history


def stack_targets(targets: list[dict]) -> dict[str, np.ndarray]:
    """Per-image target dicts stacked into batch arrays."""
    return {key: np.stack([d[key] for d in targets]) for key in targets[0]}


def train(kind: str, images, pos, ign, *, iters: int, batch: int, crop: int, lr: float, seed: int,
          device: str, init: Path | None = None, budget_s: float | None = None, log_every: int = 50,
          arch: dict | None = None):
    """Train a :class:`RockNet` (``arch``: its keyword arguments; default the kind's stride) for
    ``iters`` steps, or for ``budget_s`` seconds (see :func:`fit`); returns the model (eval mode,
    on CPU) and the loss history. ``init`` starts from saved weights (their architecture wins
    over ``arch``)."""
    import torch

    from fgslam.train.model import RockNet
    from fgslam.train.targets import make_targets

    torch.manual_seed(seed)
    rng = np.random.default_rng([seed, 5])
    net = load_weights(init) if init is not None else RockNet(**{"out_stride": OUT_STRIDE[kind], **(arch or {})})
    stride = net.out_stride

    def next_batch():
        xs, tg = [], []
        for _ in range(batch):
            k = int(rng.integers(len(images)))
            im, p, g = _crop(images[k], pos[k], ign[k], crop, rng, rotate=kind == "nadir")
            xs.append(im)
            tg.append(make_targets(p, g, crop, crop, stride))
        return np.stack(xs)[:, None].astype(np.float32), stack_targets(tg)

    return fit(net, next_batch, iters=iters, lr=lr, device=device, budget_s=budget_s, log_every=log_every, tag=kind)


def export_onnx(net, kind: str, path: Path, info: dict, flip_tta: bool = False, *,
                input_size_wh: tuple[int, int] | None = None, extra_meta: dict[str, str] | None = None) -> None:
    """Export ``net`` to ``path`` (opset 17, dynamic H/W) with the runtime's metadata (layout
    ``centernet-v1`` for rocks, ``crater-centernet-v1`` for the crater kind, plus ``extra_meta``);
    with ``flip_tta`` the graph averages the outputs of the image and its mirror image."""
    import onnx
    import torch

    from fgslam.train.model import ExportWrapper

    W, H = input_size_wh or INPUT_SIZE[kind]
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(ExportWrapper(net, flip_tta).eval(), (torch.zeros(1, 1, H, W),), str(path), dynamo=False,
                      input_names=["images"], output_names=["centernet"], opset_version=17,
                      dynamic_axes={"images": {2: "height", 3: "width"}, "centernet": {2: "h_out", 3: "w_out"}})
    model = onnx.load(str(path))
    crater = kind == "crater"
    meta = {"fgslam_layout": "crater-centernet-v1" if crater else "centernet-v1", "stride": str(net.out_stride),
            "input_size": f"{W},{H}", "kind": kind, "class_names": "crater" if crater else "rock",
            "flip_tta": str(int(flip_tta)), "train_info": json.dumps(info), **(extra_meta or {})}
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def set_metadata(path: Path, **items: str) -> None:
    """Add or replace metadata entries of the ONNX model at ``path``."""
    import onnx

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    meta.update(items)
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))


def calibrate_threshold(path: Path, kind: str, n: int, seed: int, target_precision: float | None = None) -> float:
    """Pick the operating score threshold on ``n`` rendered validation images and store it in the
    model's metadata (``score_threshold``): the highest recall at ``target_precision`` when given,
    else the widest margin to the kind's precision and recall goals (``fgslam.bench.detect.GOALS``)."""
    from fgslam.bench.detect import GOALS, pick_threshold, pick_threshold_for_goal
    from reloc.detector import DetectorConfig, RockDetector
    from sim.datasets import nadir_samples, rover_samples

    det = RockDetector(path, kind=kind, config=DetectorConfig(score_threshold=0.05))
    gen = nadir_samples(n, seed, "val") if kind == "nadir" else rover_samples(n, seed, "val")
    dets, labels = [], []
    for s in gen:
        dets.append(det.detect(s.image))
        labels.append(s.labels)
    if target_precision is not None:
        thr = pick_threshold(dets, labels, target_precision)
    else:
        thr = pick_threshold_for_goal(dets, labels, GOALS[kind]["precision"], GOALS[kind]["recall"])
    set_metadata(path, score_threshold=f"{thr:.4f}")
    return thr


def _calibrate(args: argparse.Namespace) -> None:
    thr = calibrate_threshold(args.out, args.kind, args.val_images, args.seed, args.target_precision)
    rule = "goal margin" if args.target_precision is None else f"precision {args.target_precision:.2f}"
    log.info("score threshold %.3f (%s on %d validation images)", thr, rule, args.val_images)


def _crater_main(args: argparse.Namespace) -> int:
    from fgslam.train.craters import calibrate_crater_threshold, run

    if not args.calibrate_only:
        run(args)
    if args.render_only or args.val_images <= 0:
        return 0
    thr = calibrate_crater_threshold(args.out, args.val_images, args.seed)
    log.info("crater score threshold %.3f (goal margin on %d validation images)", thr, args.val_images)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Command line of ``python -m fgslam.train``."""
    ap = argparse.ArgumentParser(prog="python -m fgslam.train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", choices=("nadir", "rover", "crater"), required=True)
    ap.add_argument("--images", type=int, default=160, help="rendered training images")
    ap.add_argument("--iters", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--minutes", type=float, default=None, help="train for this long instead of --iters")
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="CPU threads (ignored on CUDA)")
    ap.add_argument("--cache", type=Path, default=None, help=".npz cache of the rendered set")
    ap.add_argument("--render-only", action="store_true", help="only render the set into --cache")
    ap.add_argument("--init", type=Path, default=None,
                    help="start from these weights: .pt, or an exported .onnx model (batch norms folded, kept frozen)")
    ap.add_argument("--val-images", type=int, default=40, help="rendered validation images for the threshold")
    ap.add_argument("--target-precision", type=float, default=None,
                    help="operating precision (default: the widest margin to the kind's precision and recall goals)")
    ap.add_argument("--calibrate-only", action="store_true", help="only choose the threshold of the existing --out model")
    ap.add_argument("--widths", type=str, default=None, help="backbone widths c1,c2,c3,c4 (default: nadir 8,24,48,96, rover 12,32,64,128)")
    ap.add_argument("--stride", type=int, choices=(2, 4), default=None, help="output stride (default: nadir 2, rover 2)")
    ap.add_argument("--fine-width", type=int, default=None, help="channels of the stride-2 level (default: nadir 12, rover 16)")
    ap.add_argument("--flip-tta", type=int, choices=(0, 1), default=None, help="export with mirror test-time augmentation (default: 0)")
    ap.add_argument("--weights", type=Path, default=None, help="also save the trained weights (.pt) here")
    ap.add_argument("--workers", type=int, default=1, help="processes rendering the crater scenes")
    ap.add_argument("--min-scr", type=float, default=0.0,
                    help="crater: ignore targets under this photometric signal-to-clutter ratio in the crop (0: off)")
    ap.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    args = ap.parse_args(argv)
    args.command = "python -m fgslam.train " + " ".join(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.kind == "crater":
        return _crater_main(args)
    if args.calibrate_only:
        _calibrate(args)
        return 0
    import torch

    torch.set_num_threads(args.threads)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    t0 = time.perf_counter()
    if args.cache is not None and args.cache.is_file():
        images, pos, ign = load_set(args.cache)
    else:
        images, pos, ign = render_set(args.kind, args.images, args.seed)
        if args.cache is not None:
            save_set(args.cache, images, pos, ign)
    t_render = time.perf_counter() - t0
    log.info("%d images, %d rock boxes, rendered in %.0f s", len(images), sum(len(p) for p in pos), t_render)
    if args.render_only:
        return 0
    t1 = time.perf_counter()
    arch = dict(ARCH[args.kind])
    if args.widths is not None:
        arch["widths"] = tuple(int(v) for v in args.widths.split(","))
    if args.stride is not None:
        arch["out_stride"] = args.stride
    if args.fine_width is not None:
        arch["fine_width"] = args.fine_width
    flip_tta = bool(FLIP_TTA[args.kind] if args.flip_tta is None else args.flip_tta)
    net, hist = train(args.kind, images, pos, ign, iters=args.iters, batch=args.batch, crop=args.crop,
                      lr=args.lr, seed=args.seed, device=device, init=args.init,
                      budget_s=None if args.minutes is None else 60.0 * args.minutes, arch=arch)
    t_train = time.perf_counter() - t1
    info = {"images": len(images), "iters": len(hist), "arch": net.arch, "flip_tta": flip_tta, "lr": args.lr, "batch": args.batch, "crop": args.crop, "seed": args.seed,
            "device": device, "threads": args.threads, "data_s": round(t_render, 1),
            "train_s": round(t_train, 1), "final_loss": round(float(np.mean(hist[-50:])), 4)}
    if args.weights is not None:
        save_weights(net, args.weights)
    export_onnx(net, args.kind, args.out, info, flip_tta)
    if args.val_images > 0:
        _calibrate(args)
    log.info("wrote %s (%.2f MB): %s", args.out, args.out.stat().st_size / 1e6, json.dumps(info))
    return 0

"""Training targets and losses of the CenterNet-style detector.

Targets per output cell (stride ``STRIDE``): a Gaussian heatmap peaked at each object's centre
(a rock's box centre, a crater's centre; sigma grows with its size), the offset of the centre and
the log size in cells (box w, h; crater diameter) at the centre cell and (half weight) its eight
neighbours, and a weight map that is zero inside ignore boxes (too-small rocks, hidden craters),
so that the detector is neither rewarded nor punished there.
"""

from __future__ import annotations

import numpy as np

STRIDE = 4  # default output cell size in input pixels (the nadir model uses 2)


def make_targets(boxes_xyxy: np.ndarray, ignore_xyxy: np.ndarray, h_px: int, w_px: int,
                 stride: int = STRIDE) -> dict[str, np.ndarray]:
    """Targets for one image of ``h_px`` x ``w_px`` (multiples of ``stride``) from positive boxes
    (P, 4) and ignore boxes (Q, 4) in pixels: heat (h, w), weight (h, w), reg (4, h, w), mask (h, w)."""
    b = np.reshape(boxes_xyxy, (-1, 4)).astype(float)
    centres = np.column_stack([0.5 * (b[:, 0] + b[:, 2]), 0.5 * (b[:, 1] + b[:, 3])])
    sizes = np.column_stack([b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]])
    return centre_targets(centres, sizes, ignore_xyxy, h_px, w_px, stride, sigma_per_size=0.24)


def centre_targets(centres_px: np.ndarray, sizes_px: np.ndarray, ignore_xyxy: np.ndarray, h_px: int, w_px: int,
                   stride: int, sigma_per_size: float) -> dict[str, np.ndarray]:
    """Targets of objects at ``centres_px`` (P, 2) with sizes ``sizes_px`` (P, k) (box w, h; or a
    crater's diameter, k = 1) and zero-weight ``ignore_xyxy`` boxes (Q, 4): heat (h, w) with a
    Gaussian of sigma ``sigma_per_size`` x the mean size (cells) per object, weight (h, w),
    reg (2 + k, h, w) = (offset x, offset y, log sizes in cells), mask (h, w)."""
    STRIDE = stride  # the cell size of this model (shadows the module default)
    h, w = h_px // STRIDE, w_px // STRIDE
    sizes = np.asarray(sizes_px, dtype=float)
    sizes = sizes[:, None] if sizes.ndim == 1 else sizes
    k = sizes.shape[1]
    heat = np.zeros((h, w), np.float32)
    weight = np.ones((h, w), np.float32)
    reg = np.zeros((2 + k, h, w), np.float32)
    mask = np.zeros((h, w), np.float32)
    for b in np.reshape(ignore_xyxy, (-1, 4)):
        x0, y0 = int(np.floor(b[0] / STRIDE)), int(np.floor(b[1] / STRIDE))
        x1, y1 = int(np.ceil(b[2] / STRIDE)), int(np.ceil(b[3] / STRIDE))
        weight[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = 0.0
    ys, xs = np.arange(h)[:, None], np.arange(w)[None, :]
    centres = []
    for c, size in zip(np.reshape(centres_px, (-1, 2)), sizes):
        sz = size / STRIDE
        cx, cy = c[0] / STRIDE, c[1] / STRIDE
        j, i = int(cx), int(cy)
        if not (0 <= i < h and 0 <= j < w and cx >= 0 and cy >= 0) or np.any(sz <= 0):
            continue
        sigma = max(0.5, sigma_per_size * float(np.mean(sz)))
        r = int(3 * sigma) + 1
        i0, i1, j0, j1 = max(i - r, 0), min(i + r + 1, h), max(j - r, 0), min(j + r + 1, w)
        g = np.exp(-((xs[:, j0:j1] - j) ** 2 + (ys[i0:i1] - i) ** 2) / (2 * sigma**2))
        heat[i0:i1, j0:j1] = np.maximum(heat[i0:i1, j0:j1], g)
        weight[i0:i1, j0:j1] = 1.0  # an object next to an ignore box is still learned
        reg[:, i, j] = (cx - j, cy - i, *np.log(sz))
        mask[i, j] = 1.0
        centres.append((i, j, cx, cy, np.log(sz)))
    # the 8 neighbours of each centre regress the same object (half weight), so that a heat peak
    # one cell off still decodes to it; a cell that is some object's centre keeps its own
    for i, j, cx, cy, log_sz in centres:
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                a, c = i + di, j + dj
                if 0 <= a < h and 0 <= c < w and mask[a, c] == 0.0:
                    reg[:, a, c] = (cx - c, cy - a, *log_sz)
                    mask[a, c] = 0.5
    return {"heat": heat, "weight": weight, "reg": reg, "mask": mask}


def detector_loss(out, heat, weight, reg, mask, size_weight: float = 0.5):
    """Focal heatmap loss (CenterNet, alpha 2, beta 4) + L1 offset/size at centres; torch tensors:
    out (B, 1 + R, h, w) raw, heat/weight/mask (B, h, w), reg (B, R, h, w) (R = 4 for boxes, 3
    for craters). Returns (total, parts)."""
    import torch

    p = torch.sigmoid(out[:, 0]).clamp(1e-4, 1 - 1e-4)
    pos = heat >= 0.999
    neg_w = (1 - heat) ** 4
    l_pos = -(torch.log(p) * (1 - p) ** 2)[pos].sum()
    l_neg = -(torch.log(1 - p) * p**2 * neg_w * weight)[~pos].sum()
    n_pos = pos.sum().clamp(min=1).float()
    l_heat = (l_pos + l_neg) / n_pos
    m = mask.unsqueeze(1)
    l1 = (torch.abs(out[:, 1:] - reg) * m).sum(dim=(0, 2, 3)) / mask.sum().clamp(min=1)
    l_off, l_size = l1[:2].sum(), l1[2:].sum()
    total = l_heat + l_off + size_weight * l_size
    return total, {"heat": float(l_heat.detach()), "off": float(l_off.detach()), "size": float(l_size.detach())}

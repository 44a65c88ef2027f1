"""The small CenterNet-style detector (PyTorch) of the rock and crater models: a stride-16 (or,
with five widths, stride-32) backbone of plain and depthwise separable convolutions, a top-down
path back to stride 4 (or 2), and one head that predicts, per output cell, a centre heatmap
logit, the sub-cell centre offset (x, y) and the log size in output cells: box (w, h) for rocks
(``n_out`` 5), rim diameter for craters (``n_out`` 4). Default widths: 0.09 M parameters,
~0.3 GMAC on a 640 x 640 grey image; the rover model (widths 12/32/64/128, stride 2): 0.16 M
parameters."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from fgslam.train.targets import STRIDE

__all__ = ["STRIDE", "DetectorNet", "ExportWrapper", "RockNet"]
N_OUT = 5  # heat logit, offset x, offset y, log w, log h (craters: log diameter only, 4)


def _cbr(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def _dw(c: int) -> nn.Sequential:
    """Depthwise 3x3 + pointwise 1x1, each with batch norm and ReLU."""
    return nn.Sequential(
        nn.Conv2d(c, c, 3, 1, 1, groups=c, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True),
        nn.Conv2d(c, c, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True),
    )


class DetectorNet(nn.Module):
    """Input (B, C, H, W) float in [0, 1] (H, W multiples of 16, or 32 with five ``widths``);
    output (B, ``n_out``, H/s, W/s) raw with ``out_stride`` s = 4, or 2 (one more top-down level,
    for few-pixel rocks and craters). A fifth width adds a stride-32 stage: twice the receptive
    field, for craters up to tens of pixels across, at little cost."""

    def __init__(self, in_channels: int = 1, widths: tuple[int, ...] = (8, 24, 48, 96),
                 out_stride: int = 4, fine_width: int = 12, n_out: int = N_OUT) -> None:
        super().__init__()
        if out_stride not in (2, 4):
            raise ValueError(f"out_stride must be 2 or 4, got {out_stride}")
        if len(widths) not in (4, 5):
            raise ValueError(f"widths must have 4 or 5 entries, got {widths}")
        self.out_stride = out_stride
        self.arch = {"in_channels": in_channels, "widths": tuple(widths), "out_stride": out_stride, "fine_width": fine_width}
        if n_out != N_OUT:
            self.arch["n_out"] = n_out
        c1, c2, c3, c4 = widths[:4]
        self.stem = _cbr(in_channels, c1, 2)
        self.s2 = nn.Sequential(_cbr(c1, c2, 2), _dw(c2))
        self.s3 = nn.Sequential(_cbr(c2, c3, 2), _dw(c3), _dw(c3))
        self.s4 = nn.Sequential(_cbr(c3, c4, 2), _dw(c4), _dw(c4))
        if len(widths) == 5:
            c5 = widths[4]
            self.s5 = nn.Sequential(_cbr(c4, c5, 2), _dw(c5), _dw(c5))
            self.lat4 = nn.Conv2d(c5, c4, 1)
            self.fuse4 = _dw(c4)
        self.lat3 = nn.Conv2d(c4, c3, 1)
        self.fuse3 = _dw(c3)
        self.lat2 = nn.Conv2d(c3, c2, 1)
        self.fuse2 = _dw(c2)
        ch = c2
        if out_stride == 2:
            self.proj1 = nn.Conv2d(c1, fine_width, 1)
            self.lat1 = nn.Conv2d(c2, fine_width, 1)
            self.fuse1 = _dw(fine_width)
            ch = fine_width
        self.head = nn.Sequential(_dw(ch), nn.Conv2d(ch, n_out, 1))
        nn.init.constant_(self.head[-1].bias, 0.0)
        with torch.no_grad():
            self.head[-1].bias[0] = -4.0  # rare positives: start with a low heat everywhere

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f1 = self.stem(x)
        f2 = self.s2(f1)
        f3 = self.s3(f2)
        f4 = self.s4(f3)
        if hasattr(self, "s5"):
            f4 = self.fuse4(f4 + F.interpolate(self.lat4(self.s5(f4)), scale_factor=2.0, mode="nearest"))
        p3 = self.fuse3(f3 + F.interpolate(self.lat3(f4), scale_factor=2.0, mode="nearest"))
        p = self.fuse2(f2 + F.interpolate(self.lat2(p3), scale_factor=2.0, mode="nearest"))
        if self.out_stride == 2:
            p = self.fuse1(self.proj1(f1) + F.interpolate(self.lat1(p), scale_factor=2.0, mode="nearest"))
        return self.head(p)


RockNet = DetectorNet  # the name the rock models' weights were saved under


class ExportWrapper(nn.Module):
    """The deployed graph: sigmoid on the heat channel, the other four channels raw. With
    ``flip_tta`` the network also sees the left-right mirrored image and the two outputs are
    averaged cell by cell (heat after the sigmoid; the mirrored x offset o becomes 1 - o)."""

    def __init__(self, net: DetectorNet, flip_tta: bool = False) -> None:
        super().__init__()
        self.net = net
        self.flip_tta = flip_tta

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.net(x)
        heat, rest = torch.sigmoid(y[:, :1]), y[:, 1:]
        if self.flip_tta:
            yf = torch.flip(self.net(torch.flip(x, dims=[3])), dims=[3])
            heat = 0.5 * (heat + torch.sigmoid(yf[:, :1]))
            rest = 0.5 * (rest + torch.cat([1.0 - yf[:, 1:2], yf[:, 2:]], dim=1))
        return torch.cat([heat, rest], dim=1)

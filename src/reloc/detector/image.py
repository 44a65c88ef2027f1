"""Orbital image preparation for the crater detector: any bit depth to normalised grey, nodata,
and the image pyramid.

Real orbital products come as 8-bit (CTX, HiRISE browse), 10-16 bit in 16-bit containers
(HiRISE RDR) or floating point reflectance (I/F) with NaN or a fill value outside the swath.
:func:`normalised_grey` maps any of them to float32 grey levels whose 1st and 99th percentiles
over the valid pixels land on 0.1 and 0.9 (the range the network was trained on); the
statistics are of the whole image, so that a tile of it is normalised exactly as the whole is.
:func:`pyramid` halves the image by 2 x 2 averaging (pixel edges stay on pixel edges: a point
at u in level k is at u 2^k in the image).
"""

from __future__ import annotations

import cv2
import numpy as np

from reloc.detector.errors import ImageError

NORM_LOW, NORM_HIGH = 0.1, 0.9  # where the 1st and 99th percentiles of the valid pixels land
_STATS_PIXELS = 1 << 20  # percentiles from at most about this many pixels (a regular subsample)


def grey_and_valid(image: np.ndarray, nodata: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Grey float32 (H, W) and its valid mask (H, W) of an (H, W) or (H, W, 1|3|4) image of any
    integer or float dtype; NaN and inf, and ``nodata`` when given, are invalid (set to the
    median of the valid pixels in the grey image)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (1, 3, 4):
        img = img[:, :, 0] if img.shape[2] == 1 else img[:, :, :3].astype(np.float32) @ np.float32([0.299, 0.587, 0.114])
    if img.ndim != 2 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ImageError(f"image must be (H, W) grey or (H, W, 3) colour, got shape {np.shape(image)}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating) or img.dtype == bool):
        raise ImageError(f"image dtype {img.dtype} is not a number type")
    grey = img.astype(np.float32)
    valid = np.isfinite(grey)
    if nodata is not None:
        valid &= grey != np.float32(nodata)
    if not valid.any():
        raise ImageError("image has no valid pixel (all NaN, inf or nodata)")
    if not valid.all():
        grey[~valid] = np.median(grey[valid])
    return grey, valid


def normalised_grey(image: np.ndarray, nodata: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(normalised float32 grey (H, W), valid mask (H, W)) of ``image`` (module doc); a flat
    image maps to a constant 0.5."""
    grey, valid = grey_and_valid(image, nodata)
    step = max(int(np.sqrt(grey.size / _STATS_PIXELS)), 1)
    sample = grey[::step, ::step][valid[::step, ::step]]
    if sample.size == 0:
        sample = grey[valid]
    lo, hi = np.percentile(sample, [1.0, 99.0])
    if not hi > lo:
        lo, hi = float(sample.min()), float(sample.max())
    if not hi > lo:
        return np.full(grey.shape, 0.5, np.float32), valid
    scale = np.float32((NORM_HIGH - NORM_LOW) / (hi - lo))
    out = (grey - np.float32(lo)) * scale + np.float32(NORM_LOW)
    return out, valid


def half(image: np.ndarray) -> np.ndarray:
    """``image`` (H, W) float32 at half resolution by 2 x 2 averaging (odd edges: the last row or
    column averaged with itself), shape (ceil(H/2), ceil(W/2))."""
    h, w = image.shape
    if h % 2 or w % 2:
        image = cv2.copyMakeBorder(image, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)
    return cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)


def pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """``levels`` images: ``image`` and its successive halvings (:func:`half`)."""
    out = [image]
    for _ in range(levels - 1):
        out.append(half(out[-1]))
    return out

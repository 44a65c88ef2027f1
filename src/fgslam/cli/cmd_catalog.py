"""``fgslam catalog``: a rock or crater catalog (x,y,size,score CSV) from any nadir image."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from fgslam.cli.app import app

TIFF_SUFFIXES = (".tif", ".tiff")


def read_nadir_image(path: Path):
    """The image at ``path`` as an array: (H, W) grey or (H, W, 3) RGB, its own dtype (8/16-bit
    integer, float); TIFFs through tifffile (float and large files), the rest through OpenCV."""
    import cv2
    import numpy as np

    from fgslam.errors import InputFileError

    if not path.is_file():
        raise InputFileError(f"{path}: image file not found")
    img = None
    if path.suffix.lower() in TIFF_SUFFIXES:
        import tifffile

        try:
            img = tifffile.imread(str(path))
        except Exception as exc:  # tifffile raises several types for damaged files
            raise InputFileError(f"{path}: not a readable TIFF ({exc})") from None
        img = np.squeeze(img)
        if img.size == 0:
            raise InputFileError(f"{path}: not a readable TIFF (no image data)")
        if img.ndim == 3 and img.shape[0] in (3, 4) and img.shape[2] not in (3, 4):
            img = np.moveaxis(img, 0, 2)  # planar RGB
        if img.ndim == 3 and img.shape[2] == 4:
            img = img[:, :, :3]
    else:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputFileError(f"{path}: not an image OpenCV can read")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3) or min(img.shape[:2]) < 1:
        raise InputFileError(f"{path}: image of shape {img.shape}, expected (H, W) grey or (H, W, 3) colour")
    if img.dtype.kind not in "uif":
        raise InputFileError(f"{path}: pixel type {img.dtype} is not a number type")
    return img


def _rock_image(img):
    """8-bit image for the rock detector (min-max stretched when it is not 8-bit)."""
    import cv2
    import numpy as np

    if img.dtype == np.uint8:
        return img
    img = np.nan_to_num(img.astype(np.float32), nan=float(np.nanmedian(img)))
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


@app.command("catalog")
def catalog_cmd(
    image: Path = typer.Argument(..., help="Nadir image (PNG, JPEG, TIFF, JPEG 2000; grey or colour; 8/16-bit or float)."),
    gsd: float = typer.Option(..., "--gsd", help="Ground sample distance in metres per pixel."),
    origin: tuple[float, float] = typer.Option((0.0, 0.0), "--origin", help="World X Y (m) of the image's top-left corner (row 0 is north)."),
    out: Path = typer.Option(..., "--out", help="Catalog CSV to write (x,y,size,score; size = rock or rim diameter, m)."),
    landmark: str = typer.Option("rock", "--landmark", help="Landmark kind to detect: rock or crater."),
    model: Path | None = typer.Option(None, "--model", help="ONNX detector (default: the shipped model of the landmark kind; Ultralytics YOLO exports work for rocks)."),
    score_threshold: float | None = typer.Option(None, "--score-threshold", help="Minimum detector score (default: the model's)."),
    nodata: float | None = typer.Option(None, "--nodata", help="Pixel value outside the image footprint (craters; NaN always is)."),
    threads: int = typer.Option(1, "--threads", help="onnxruntime threads."),
) -> None:
    """Detect rocks or craters in a nadir IMAGE and write their world positions and diameters as a catalog."""
    import time

    from rich.console import Console

    from fgslam.errors import InputFileError
    from fgslam.io.catalog_csv import MIN_CATALOG_ROCKS, write_catalog_csv
    from fgslam.io.outdir import atomic_path, check_output_path
    from reloc.detector import (
        DetectorConfig,
        catalog_from_detections,
        orbital_detector,
        orbital_landmarks,
    )

    if landmark not in orbital_landmarks():
        raise InputFileError(f"--landmark must be one of {', '.join(orbital_landmarks())}, got {landmark!r}")
    if not (math.isfinite(gsd) and gsd > 0):
        raise InputFileError(f"--gsd must be a finite ground sample distance > 0 m/px, got {gsd}")
    if not all(math.isfinite(v) for v in origin):
        raise InputFileError(f"--origin must be two finite numbers X Y (m), got {origin[0]} {origin[1]}")
    if score_threshold is not None and not 0.0 <= score_threshold <= 1.0:
        raise InputFileError(f"--score-threshold must be in [0, 1], got {score_threshold}")
    if threads < 1:
        raise InputFileError(f"--threads must be >= 1, got {threads}")
    check_output_path(out, "--out", directory=False)  # before the image is read and searched
    img = read_nadir_image(image)
    t0 = time.perf_counter()
    config = DetectorConfig(score_threshold=score_threshold, threads=threads)
    if landmark == "crater":
        dets = orbital_detector(landmark, model, config, nodata=nodata).detect(img)
    else:
        if nodata is not None:
            raise InputFileError("--nodata applies to --landmark crater only")
        dets = orbital_detector(landmark, model, config).detect(_rock_image(img))
    catalog = catalog_from_detections(dets, gsd, origin)
    kind = {"rock": "rocks", "crater": "craters"}.get(landmark, landmark)
    if len(catalog) < MIN_CATALOG_ROCKS:  # `fgslam run` would reject the file: write none
        raise InputFileError(
            f"{image}: {len(catalog)} {kind} detected, a catalog needs at least {MIN_CATALOG_ROCKS}; "
            f"is it a nadir image at {gsd} m/px? (a lower --score-threshold finds more); {out} not written")
    with atomic_path(out) as tmp:
        write_catalog_csv(tmp, catalog)
    Console(stderr=True).print(
        f"{len(catalog)} {kind} from {image} ({img.shape[1]} x {img.shape[0]} px, {img.dtype}, {gsd} m/px) "
        f"in {time.perf_counter() - t0:.2f} s -> {out}")

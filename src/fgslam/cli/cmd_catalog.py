"""``fgslam catalog``: a rock catalog (x,y,size,score CSV) from any nadir image."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fgslam.cli.app import app


@app.command("catalog")
def catalog_cmd(
    image: Path = typer.Argument(..., help="Nadir image (PNG, JPEG, TIFF; grey or colour)."),
    gsd: float = typer.Option(..., "--gsd", help="Ground sample distance in metres per pixel."),
    origin: tuple[float, float] = typer.Option((0.0, 0.0), "--origin", help="World X Y (m) of the image's top-left corner (row 0 is north)."),
    out: Path = typer.Option(..., "--out", help="Catalog CSV to write (x,y,size,score)."),
    model: Optional[Path] = typer.Option(None, "--model", help="ONNX detector (default: the shipped nadir model; Ultralytics YOLO exports work too)."),
    score_threshold: Optional[float] = typer.Option(None, "--score-threshold", help="Minimum detector score (default: the model's)."),
    threads: int = typer.Option(1, "--threads", help="onnxruntime threads."),
) -> None:
    """Detect rocks in a nadir IMAGE and write their world positions and diameters as a catalog."""
    import math
    import time

    import cv2
    from rich.console import Console

    from fgslam.errors import InputFileError
    from fgslam.io.catalog_csv import MIN_CATALOG_ROCKS, write_catalog_csv
    from fgslam.io.outdir import atomic_path, check_output_path
    from reloc.detector import DetectorConfig, RockDetector, catalog_from_detections

    if not (math.isfinite(gsd) and gsd > 0):
        raise InputFileError(f"--gsd must be a finite number > 0 m/px, got {gsd}")
    if not all(math.isfinite(v) for v in origin):
        raise InputFileError(f"--origin must be two finite numbers X Y (m), got {origin[0]} {origin[1]}")
    if score_threshold is not None and not 0.0 <= score_threshold <= 1.0:
        raise InputFileError(f"--score-threshold must be in [0, 1], got {score_threshold}")
    if threads < 1:
        raise InputFileError(f"--threads must be >= 1, got {threads}")
    check_output_path(out, "--out", directory=False)  # before the image is read and searched
    if not image.is_file():
        raise InputFileError(f"{image}: image file not found")
    img = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(f"{image}: not an image OpenCV can read")
    if img.dtype != "uint8":
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    t0 = time.perf_counter()
    det = RockDetector(model, kind="nadir", config=DetectorConfig(score_threshold=score_threshold, threads=threads))
    dets = det.detect(img)
    catalog = catalog_from_detections(dets, gsd, origin)
    if len(catalog) < MIN_CATALOG_ROCKS:  # `fgslam run` would reject the file: write none
        raise InputFileError(
            f"{image}: {len(catalog)} rock(s) detected, a catalog needs at least {MIN_CATALOG_ROCKS}; "
            f"is it a nadir image at {gsd} m/px? (a lower --score-threshold finds more); {out} not written")
    with atomic_path(out) as tmp:
        write_catalog_csv(tmp, catalog)
    Console(stderr=True).print(
        f"{len(catalog)} rocks from {image} ({img.shape[1]} x {img.shape[0]} px, {gsd} m/px) "
        f"in {time.perf_counter() - t0:.2f} s -> {out}")

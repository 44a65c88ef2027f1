"""``fgslam bench detect``: detector quality (Table I shape) and timings on held-out rendered worlds."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fgslam.cli.app import bench_app


@bench_app.command("detect")
def bench_detect_cmd(
    nadir_images: int = typer.Option(24, "--nadir-images", help="Held-out nadir tiles (640 x 640)."),
    rover_images: int = typer.Option(40, "--rover-images", help="Held-out rover views (640 x 360)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the held-out worlds (eval stream)."),
    nadir_model: Optional[Path] = typer.Option(None, "--nadir-model", help="Nadir ONNX model (default: shipped)."),
    rover_model: Optional[Path] = typer.Option(None, "--rover-model", help="Rover ONNX model (default: shipped)."),
    quick: bool = typer.Option(False, "--quick", help="Few images (a smoke run)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Directory for results.json and table.md."),
) -> None:
    """Precision, recall, mAP50, mAP50-95 of the nadir and rover detectors, inference and render timings."""

    from rich.console import Console

    from fgslam.cli.bench_output import check_out, print_tables, progress_ticks, write_results

    check_out(out)

    from fgslam.bench.detect import DetectBenchConfig, markdown, result_rows, run_detect_bench, timing_rows

    cfg = DetectBenchConfig(
        nadir_images=3 if quick else nadir_images, rover_images=4 if quick else rover_images, seed=seed,
        timing_runs=5 if quick else 20, nadir_model=None if nadir_model is None else str(nadir_model),
        rover_model=None if rover_model is None else str(rover_model))
    err = Console(stderr=True)
    with progress_ticks(err, label_width=45) as tick:
        res = run_detect_bench(cfg, progress=tick)
    print_tables(
        [
            ("Rock detectors on held-out rendered worlds", *result_rows(res)),
            ("Timings (one thread: onnxruntime, open3d, OpenCV)", *timing_rows(res)),
        ],
        width=160,
    )
    write_results(out, res, markdown(res), err)

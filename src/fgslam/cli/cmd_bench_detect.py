"""``fgslam bench detect``: detector quality (Table I shape) and timings on held-out rendered worlds."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app

LANDMARKS = ("rock", "crater")


@bench_app.command("detect")
def bench_detect_cmd(
    landmark: str = typer.Option("rock", "--landmark", help="Landmark kind: rock (nadir and rover models) or crater (orbital model)."),
    nadir_images: int = typer.Option(24, "--nadir-images", help="Held-out nadir tiles (640 x 640)."),
    rover_images: int = typer.Option(40, "--rover-images", help="Held-out rover views (640 x 360)."),
    crater_images: int = typer.Option(12, "--crater-images", help="Held-out cratered images (--crater-image-px square)."),
    crater_image_px: int = typer.Option(1024, "--crater-image-px", help="Side of the held-out cratered images, px."),
    seed: int = typer.Option(0, "--seed", help="Seed of the held-out worlds (eval stream)."),
    nadir_model: Path | None = typer.Option(None, "--nadir-model", help="Nadir ONNX model (default: shipped)."),
    rover_model: Path | None = typer.Option(None, "--rover-model", help="Rover ONNX model (default: shipped)."),
    crater_model: Path | None = typer.Option(None, "--crater-model", help="Crater ONNX model (default: shipped)."),
    quick: bool = typer.Option(False, "--quick", help="Few images (a smoke run)."),
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json and table.md."),
) -> None:
    """Precision, recall, mAP50, mAP50-95 of the detectors of a landmark kind (craters also centre
    and diameter errors), inference and render timings."""

    from rich.console import Console

    from fgslam.cli.bench_output import check_out, print_tables, progress_ticks, write_results
    from fgslam.errors import InputFileError

    check_out(out)

    if landmark not in LANDMARKS:
        raise InputFileError(f"--landmark must be one of {', '.join(LANDMARKS)}, got {landmark!r}")
    err = Console(stderr=True)
    if landmark == "crater":
        from fgslam.bench.detect_craters import (
            CraterBenchConfig,
            crater_markdown,
            crater_rows,
            crater_scr_rows,
            crater_timing_rows,
            run_crater_bench,
        )

        if crater_images < 1 or crater_image_px < 64:
            raise InputFileError(f"--crater-images must be >= 1 and --crater-image-px >= 64, got {crater_images}, {crater_image_px}")
        ccfg = CraterBenchConfig(images=2 if quick else crater_images, image_px=640 if quick else crater_image_px,
                                 seed=seed, timing_runs=3 if quick else 10,
                                 model=None if crater_model is None else str(crater_model))
        with progress_ticks(err, label_width=45) as tick:
            res = run_crater_bench(ccfg, progress=tick)
        print_tables([("Crater detector on held-out rendered worlds", *crater_rows(res)),
                      ("By photometric signal-to-clutter ratio (craters >= 8 px)", *crater_scr_rows(res)),
                      ("Crater detector timing (one thread)", *crater_timing_rows(res))], width=170)
        write_results(out, res, crater_markdown(res), err)
        return

    from fgslam.bench.detect import (
        DetectBenchConfig,
        markdown,
        result_rows,
        run_detect_bench,
        timing_rows,
    )

    cfg = DetectBenchConfig(
        nadir_images=3 if quick else nadir_images, rover_images=4 if quick else rover_images, seed=seed,
        timing_runs=5 if quick else 20, nadir_model=None if nadir_model is None else str(nadir_model),
        rover_model=None if rover_model is None else str(rover_model))
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

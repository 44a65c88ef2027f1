"""``fgslam bench match``: the constellation matcher's goals, measured, side by side with astroalign."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


def _ints(text: str | None) -> tuple[int, ...] | None:
    return None if text is None else tuple(int(v) for v in text.split(",") if v.strip())


def _floats(text: str | None) -> tuple[float, ...] | None:
    return None if text is None else tuple(float(v) for v in text.split(",") if v.strip())


@bench_app.command("match")
def bench_match_cmd(
    quick: bool = typer.Option(False, "--quick", help="Small run (about a minute)."),
    sizes: str | None = typer.Option(None, "--sizes", help="Catalog sizes, e.g. 300,3000,100000."),
    layouts: str | None = typer.Option(None, "--layouts", help="uniform,clustered"),
    sigmas: str | None = typer.Option(None, "--sigmas", help="Position noise levels (m), e.g. 0.05,0.2."),
    queries: int | None = typer.Option(None, "--queries", help="Queries per (size, layout, sigma)."),
    outside_queries: int | None = typer.Option(None, "--outside-queries", help="Out-of-catalog queries per setting."),
    detector_queries: int | None = typer.Option(None, "--detector-queries", help="Queries per layout with detector qualities."),
    astro_queries: int | None = typer.Option(None, "--astro-queries", help="Queries also given to astroalign (0: skip)."),
    astro_sizes: str | None = typer.Option(None, "--astro-sizes", help="Catalog sizes compared with astroalign."),
    astro_timeout: float | None = typer.Option(None, "--astro-timeout", help="Seconds before an astroalign try counts as no answer."),
    runner_queries: int | None = typer.Option(None, "--runner-queries", help="Runner-like queries (80 rocks, prior; 0: skip)."),
    build_size: int | None = typer.Option(None, "--build-size", help="Rocks of the index-build measurement."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random draw."),
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json and table.md."),
) -> None:
    """Success, false matches, accuracy, speed and index build of the matcher (tables on stdout)."""
    import dataclasses

    from rich.console import Console

    from fgslam.cli.bench_output import check_out, print_tables, progress_ticks, write_results

    check_out(out)

    from fgslam.bench.match import (
        MatchBenchConfig,
        quick_config,
        result_tables,
        run_match_bench,
        tables_markdown,
    )

    cfg = quick_config(seed) if quick else MatchBenchConfig(seed=seed)
    overrides = {
        "sizes": _ints(sizes), "layouts": None if layouts is None else tuple(layouts.split(",")),
        "sigmas_m": _floats(sigmas), "queries": queries, "outside_queries": outside_queries,
        "detector_queries": detector_queries, "astro_queries": astro_queries,
        "astro_sizes": _ints(astro_sizes), "build_size": build_size,
        "astro_timeout_s": astro_timeout, "runner_queries": runner_queries,
    }
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    err = Console(stderr=True)
    with progress_ticks(err, label_width=40) as tick:
        res = run_match_bench(cfg, progress=tick)
    print_tables(result_tables(res), width=220)
    write_results(out, res, tables_markdown(res), err)

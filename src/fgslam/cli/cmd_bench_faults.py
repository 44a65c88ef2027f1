"""``fgslam bench faults``: the fault-scenario table of both back-ends (docs/sim.md, "Faults")."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("faults")
def bench_faults_cmd(
    out: Path = typer.Option(..., "--out", help="Output directory (table.md, results.json, config.yaml)."),
    world: str = typer.Option("my2020", "--world", help="Yard preset (my2020, my2021, my2022, cnes) or a Gazebo model directory."),
    seed: str = typer.Option("0", "--seed", help="Seed of every random process of the runs (faults included); several "
                             "(0-2 or 0,3,7) run the table once per seed and pool it across them."),
    distance_m: float = typer.Option(24.0, "--distance-m", help="Traverse length in metres."),
    only: str | None = typer.Option(None, "--only", help="Comma-separated scenarios (the fault-free one always runs)."),
    config: Path | None = typer.Option(None, "--config", help="YAML overrides of the simulator config (no faults block: the scenarios set it)."),
    compare_config: Path | None = typer.Option(None, "--compare-config", help="YAML overrides of the comparison config."),
) -> None:
    """Simulate a short traverse once per fault scenario, run EKF and iSAM2 (each with and without
    relocalization) on each, and tabulate consistency while blind and the error at the end."""
    import yaml
    from rich.console import Console

    from fgslam.bench.faults import (
        FaultBenchConfig,
        markdown,
        markdown_pooled,
        pooled,
        run_fault_bench,
        scenarios,
    )
    from fgslam.campaign.spec import CampaignError, parse_seeds
    from fgslam.cli.bench_output import check_out, progress_ticks
    from fgslam.cli.cmd_run import load_config
    from fgslam.config_file import read_yaml_mapping, sim_overrides
    from fgslam.io.outdir import OutputDir
    from fgslam.report import _jsonable
    from reloc.config import config_to_dict
    from sim.world import PRESETS

    if world not in PRESETS and not Path(world).is_dir():
        raise typer.BadParameter(f"unknown world {world!r}: use one of {sorted(PRESETS)} or a Gazebo model directory",
                                 param_hint="--world")
    if not distance_m > 0 or not distance_m < float("inf"):
        raise typer.BadParameter(f"must be > 0, got {distance_m}", param_hint="--distance-m")
    try:
        seeds = parse_seeds(seed)
    except CampaignError as exc:
        raise typer.BadParameter(str(exc).replace("--seeds", "seed"), param_hint="--seed") from None
    check_out(out)
    cfg = FaultBenchConfig(world=world, seed=seeds[0], distance_m=distance_m)
    names = None
    if only is not None:
        names = tuple(s.strip() for s in only.split(",") if s.strip())
        unknown = sorted(set(names) - set(scenarios(cfg)))
        if unknown:
            raise typer.BadParameter(f"unknown scenario(s) {unknown}; choose from {list(scenarios(cfg))}", param_hint="--only")
    overrides = sim_overrides(read_yaml_mapping(config, "simulator config")) if config is not None else {}
    if "faults" in overrides:
        raise typer.BadParameter("the scenarios set the faults block; remove it from the file", param_hint="--config")
    cmp_cfg = load_config(compare_config)
    err = Console(stderr=True)
    by_seed = {}
    with progress_ticks(err) as tick:
        for sd in seeds:
            by_seed[sd] = run_fault_bench(dataclasses.replace(cfg, seed=sd), cmp_cfg, overrides, tick=tick, only=names)
    if len(seeds) == 1:
        res = by_seed[seeds[0]]
        table = markdown(res)
    else:
        pool = pooled(by_seed)
        res = {"seeds": list(seeds), "pooled": pool, "by_seed": {str(k): v for k, v in by_seed.items()}}
        table = "\n".join([markdown_pooled(by_seed, pool)] + [markdown(r) for r in by_seed.values()])
    with OutputDir(out, "bench") as od:
        import json

        (od.staging / "results.json").write_text(json.dumps(_jsonable(res), indent=2))
        (od.staging / "table.md").write_text(table)
        used = {"bench": config_to_dict(cfg) | {"seed": list(seeds) if len(seeds) > 1 else seeds[0]},
                "sim_overrides": overrides, "compare_config": by_seed[seeds[0]]["compare_config"],  # as run (draw_start set)
                "scenarios": {k: config_to_dict(v) for k, v in scenarios(cfg).items()}}
        (od.staging / "config.yaml").write_text(yaml.safe_dump(_jsonable(used), sort_keys=False))
        files = od.commit()
    typer.echo(table)
    err.print("wrote " + ", ".join(str(f) for f in files))

"""``fgslam bench isam2``: the smoother's speed and accuracy goals, as tables (and results.json)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("isam2")
def bench_isam2_cmd(
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json."),
    quick: bool = typer.Option(False, "--quick", help="Short runs (200 s traverse, 100 m fixed-lag)."),
    source: str = typer.Option("sim", "--source", help="Traverse source: 'sim' (simulator) or 'synthetic'."),
    world: str = typer.Option("my2021", "--world", help="Simulator world of the traverse."),
    seed: int = typer.Option(1, "--seed", help="Seed of the traverses and the synthetic fixes."),
    duration_s: float = typer.Option(1000.0, "--duration-s", help="Duration of the traverse with fixes."),
    distance_m: float = typer.Option(1000.0, "--distance-m", help="Length of the fixed-lag traverse."),
    lag_s: float = typer.Option(60.0, "--lag-s", help="Window of the fixed-lag smoother."),
    ekf: bool = typer.Option(True, "--ekf/--no-ekf", help="Run the EKF on the same traverse and fixes."),
    skip_fixed_lag: bool = typer.Option(False, "--skip-fixed-lag", help="Only the traverse with fixes."),
    skip_traverse: bool = typer.Option(False, "--skip-traverse", help="Only the fixed-lag traverse."),
) -> None:
    """Traverse with late fixes (real-time factor, latency, ATE vs EKF, wrong fixes) and a long
    fixed-lag traverse (latency and memory against distance)."""
    from rich.console import Console

    from fgslam.cli.bench_output import check_out, write_results
    from fgslam.smoother import SmootherConfig

    check_out(out)

    if quick:
        duration_s, distance_m = min(duration_s, 200.0), min(distance_m, 100.0)
    console = Console(width=max(Console().width, 120))
    results: dict = {"seed": seed, "source": source, "world": world, "quick": quick}
    cfg = SmootherConfig()
    if not skip_traverse:
        _traverse(console, results, source, world, seed, duration_s, cfg, ekf)
    if not skip_fixed_lag:
        _fixed_lag(console, results, seed, distance_m, lag_s)
    write_results(out, results, None, console)


def _traverse(console, results: dict, source: str, world: str, seed: int, duration_s: float, cfg, ekf: bool) -> None:
    from rich.progress import Progress
    from rich.table import Table

    from fgslam.bench.isam2 import make_scenario, traverse_benchmark

    with console.status(f"generating a {duration_s:.0f} s traverse ({source}, seed {seed})"):
        run = make_scenario(source, seed, duration_s, world)
    with Progress(console=console, transient=True) as progress:
        n_runs = 6 if ekf else 3
        task = progress.add_task("traverse runs", total=n_runs)
        tr = traverse_benchmark(run, seed, cfg, with_ekf=ekf,
                                progress=lambda name: progress.update(task, advance=1, description=name))
    results["traverse"] = tr
    table = Table(title=f"{tr['duration_s']:.0f} s traverse, {tr['distance_m']:.0f} m ({source} {world if source == 'sim' else ''} "
                        f"seed {seed}), fixes every 11 s, 1-30 s late")
    for col in ("back-end", "fixes", "RT x wall/cpu", "med ms wall/cpu", "p99 ms wall/cpu", "ATE [m]",
                "online [m]", "acc.", "wrong acc/retr"):
        table.add_column(col, justify="right")
    for r in tr["runs"]:
        table.add_row(
            r["backend"], {"no_fixes": "none", "fixes": "good", "fixes_10pct_wrong": "+10% wrong"}[r["case"]],
            f"{r['real_time_factor']:.0f}/{r['real_time_factor_cpu']:.0f}",
            f"{r['latency_median_ms']:.1f}/{r['latency_cpu_median_ms']:.1f}" if "latency_median_ms" in r else "-",
            f"{r['latency_p99_ms']:.1f}/{r['latency_cpu_p99_ms']:.1f}" if "latency_p99_ms" in r else "-",
            f"{r['ate_final_m']:.3f}", f"{r['ate_online_m']:.3f}", f"{r['n_accepted']}/{r['n_fixes']}",
            f"{r['n_wrong_accepted']}/{r.get('n_wrong_retracted', '-')} of {r['n_wrong']}" if r["n_wrong"] else "-",
        )
    console.print(table)


def _fixed_lag(console, results: dict, seed: int, distance_m: float, lag_s: float) -> None:
    from rich.progress import Progress
    from rich.table import Table

    from fgslam.bench.isam2 import fixed_lag_benchmark

    with Progress(console=console, transient=True) as progress:
        task = progress.add_task(f"fixed-lag {distance_m:.0f} m", total=distance_m / 0.3)
        fl = fixed_lag_benchmark(distance_m, seed, lag_s, progress=lambda t: progress.update(task, completed=t))
    results["fixed_lag"] = fl
    t2 = Table(title=f"fixed-lag ({lag_s:.0f} s) synthetic traverse: {fl['distance_m']:.0f} m, "
               f"{fl['n_keyframes']} keyframes, real-time x{fl['real_time_factor']:.0f} wall / x{fl['real_time_factor_cpu']:.0f} cpu, "
               f"ATE {fl['ate_final_m']:.3f} m")
    for col in ("up to [m]", "updates", "median ms wall/cpu", "p99 ms wall/cpu", "RSS [MB]", "keys in window"):
        t2.add_column(col, justify="right")
    for b in fl["bins"]:
        t2.add_row(f"{b['distance_m']:.0f}", str(b["n_updates"]),
                   f"{b['latency_median_ms']:.2f}/{b['latency_cpu_median_ms']:.2f}",
                   f"{b['latency_p99_ms']:.2f}/{b['latency_cpu_p99_ms']:.2f}", f"{b['rss_mb']:.1f}", str(b["alive_keys"]))
    console.print(t2)

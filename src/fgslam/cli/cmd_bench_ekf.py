"""``fgslam bench ekf``: EKF-SLAM per-step cost against the landmark count, and a long simulated
traverse (real-time factor on one core, ATE without and with synthetic late fixes)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import bench_app


@bench_app.command("ekf")
def bench_ekf_cmd(
    out: Path | None = typer.Option(None, "--out", help="Directory for results.json."),
    world: str = typer.Option("my2021", "--world", help="Simulator world of the traverse benchmark."),
    seed: int = typer.Option(1, "--seed", help="Seed of the simulated traverse and the synthetic fixes."),
    duration_s: float = typer.Option(1000.0, "--duration-s", help="Traverse duration (inputs at 30 Hz)."),
    distance_m: float = typer.Option(66.0, "--distance-m", help="Traverse length in metres."),
    max_landmarks: int = typer.Option(300, "--max-landmarks", help="Bound on the EKF landmark count."),
    curve: str = typer.Option("0,25,50,100,200,300,500", "--curve", help="Landmark counts of the cost curve."),
    skip_traverse: bool = typer.Option(False, "--skip-traverse", help="Only the cost curve."),
    threads: int = typer.Option(1, "--threads", help="BLAS threads (the goal is stated for one core)."),
) -> None:
    """Cost curve (predict / landmark frame vs landmark count) and the 1000 s traverse benchmark."""
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from fgslam.bench.ekf import cost_curve, traverse_benchmark
    from fgslam.cli.bench_output import check_out, write_results

    check_out(out)

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it the BLAS thread count is the library default
        threadpool_limits = None
    console = Console()
    ns = [int(x) for x in curve.split(",") if x.strip()]
    results: dict = {"threads": threads}
    import contextlib

    with threadpool_limits(limits=threads) if threadpool_limits else contextlib.nullcontext():
        with Progress(console=console, transient=True) as progress:
            task = progress.add_task("cost curve", total=len(ns))
            points = cost_curve(ns, seed, progress=lambda n: progress.advance(task))
        table = Table(title=f"EKF per-step cost vs landmark count ({threads} BLAS thread)")
        for col in ("landmarks", "state dim", "predict (ms)", "frame, 15 det. (ms)"):
            table.add_column(col, justify="right")
        for p in points:
            table.add_row(str(p.n_landmarks), str(p.state_dim), f"{p.predict_ms:.3f}", f"{p.frame_ms:.2f}")
        console.print(table)
        results["cost_curve"] = [p.__dict__ for p in points]
        if not skip_traverse:
            with console.status(f"simulating and running a {duration_s:.0f} s traverse in {world} (seed {seed})"):
                tr = traverse_benchmark(world, seed, duration_s, distance_m, max_landmarks)
            results["traverse"] = tr
            t = Table(title=f"{tr['duration_s']:.0f} s traverse, {tr['distance_m']:.1f} m, {world} seed {seed}, "
                            f"IMU {tr['imu_rate_hz']:.0f} Hz, {tr['n_rock_frames']} rock frames, max {max_landmarks} landmarks")
            for col in ("run", "EKF CPU (s)", "RTF (CPU)", "EKF wall (s)", "RTF (wall)", "ATE RMSE (m)", "ATE max (m)", "fixes acc/all"):
                t.add_column(col, justify="right")
            nf, wf = tr["no_fixes"], tr["with_synthetic_fixes"]
            t.add_row("no fixes", f"{nf['ekf_cpu_s']:.1f}", f"{nf['real_time_factor_cpu']:.0f}x",
                      f"{nf['ekf_wall_s']:.1f}", f"{nf['real_time_factor']:.0f}x",
                      f"{nf['ate']['rmse']:.3f}", f"{nf['ate']['max']:.3f}", "-")
            t.add_row("synthetic late fixes", f"{wf['ekf_cpu_s']:.1f}", f"{wf['real_time_factor_cpu']:.0f}x",
                      f"{wf['ekf_wall_s']:.1f}", f"{wf['real_time_factor']:.0f}x",
                      f"{wf['ate']['rmse']:.3f}", f"{wf['ate']['max']:.3f}", f"{wf['n_accepted']}/{wf['n_fixes']}")
            console.print(t)
            goal = nf["real_time_factor_cpu"] >= 50.0
            console.print(f"real-time goal (>= 50x on one core, CPU time of this process): {'met' if goal else 'NOT met'}; "
                          f"final landmarks {nf['n_landmarks_final']}, state dim {nf['state_dim_final']}")
    write_results(out, results, None, console, json_default=str)

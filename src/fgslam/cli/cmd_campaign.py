"""``fgslam campaign``: Monte Carlo comparison over worlds x seeds (x variants) on Dask."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


@app.command("campaign")
def campaign_cmd(
    worlds: str = typer.Option(..., "--worlds", help="Comma-separated worlds: yard presets (my2020, my2021, my2022, cnes), kilometre presets (plains-2km, rocky-1km, cratered-3km, sparse-5km: streamed through a temporary bag on the worker, with their backend.yaml) or Gazebo model directories."),
    seeds: str = typer.Option(..., "--seeds", help="Simulator seeds: 0-9, 0,3,7 or 0-3,10-12."),
    out: Path = typer.Option(..., "--out", help="Output directory (results.jsonl, summary.md, summary.json, campaign.json)."),
    scheduler: str | None = typer.Option(None, "--scheduler", help="Address of an existing Dask scheduler (tcp://host:8786); default: a local cluster."),
    workers: int = typer.Option(2, "--workers", help="Worker processes of the local cluster (one thread each)."),
    set_: list[str] = typer.Option([], "--set", help="Override for every task, dotted: traverse.distance_m=50, relocalizer.period_s=5 (repeatable)."),
    vary: list[str] = typer.Option([], "--vary", help="Sweep as variants: relocalizer.period_s=2,3,5 (repeatable; combinations of all sweeps)."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUT that fgslam did not create (its other files are kept)."),
) -> None:
    """Simulate each (world, seed), compare EKF and iSAM2 with and without relocalization on Dask,
    append results to OUT/results.jsonl (rerun to resume) and summarise across seeds."""
    import logging
    import time

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from fgslam.campaign import (
        CampaignSpec,
        expand,
        parse_overrides,
        parse_seeds,
        require_dask,
        run_campaign,
        variants_from_sweeps,
    )
    from fgslam.campaign.aggregate import write_summary
    from fgslam.io.outdir import COMPLETE, INCOMPLETE, OutputDir

    console = Console(stderr=True)
    require_dask()  # a clear error before any work; importing distributed also sets its log levels
    logging.getLogger("distributed").setLevel(logging.WARNING)  # its INFO chatter would hide the progress bar
    names = tuple(w.strip() for w in worlds.split(",") if w.strip())
    spec = CampaignSpec(worlds=names, seeds=parse_seeds(seeds), overrides=parse_overrides(set_),
                        variants=variants_from_sweeps(vary))
    n_tasks = len(expand(spec))  # every variant's configs checked before the directory is touched
    where = f"scheduler {scheduler}" if scheduler else f"a local cluster of {workers} worker(s)"
    console.print(f"campaign: {len(names)} world(s) x {len(spec.seeds)} seed(s) x {len(spec.variants)} "
                  f"variant(s) = {n_tasks} tasks on {where}")
    counts = {"ok": 0, "error": 0}
    t0 = time.perf_counter()
    with OutputDir(out, "campaign", staged=False, force=force) as od:  # checked and locked before the cluster starts
        od.write_manifest(INCOMPLETE, tasks=n_tasks)
        with Progress(TextColumn("{task.description:<34}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=console) as progress:
            bar = progress.add_task("starting the cluster", total=None)

            def on_start(to_run: int, skipped: int) -> None:
                if skipped:
                    console.print(f"resuming: {skipped} task(s) already done in {out / 'results.jsonl'}")
                progress.update(bar, total=to_run, description="tasks")

            def on_result(rec: dict) -> None:
                counts["ok" if rec["status"] == "ok" else "error"] += 1
                if rec["status"] != "ok":
                    progress.console.print(f"[red]failed[/red] {rec['key']}: {rec.get('error', '')}")
                progress.update(bar, advance=1, description=f"tasks ({counts['ok']} ok, {counts['error']} failed)")

            try:
                run = run_campaign(spec, out, scheduler=scheduler, n_workers=workers, on_start=on_start, on_result=on_result)
            except KeyboardInterrupt:
                console.print(f"interrupted; finished tasks are in {out / 'results.jsonl'}; rerun the same command to resume")
                raise typer.Exit(130) from None
        extra = {"campaign": spec.to_dict(),
                 "last_invocation": {"wall_s": run.wall_s, "computed": run.computed, "skipped": run.skipped,
                                     "workers": run.n_workers, "scheduler": scheduler or "local"}}
        md, js = write_summary(out, run.records, extra)
        failed = sum(r["status"] != "ok" for r in run.records)
        ok = sum(r["status"] == "ok" for r in run.records)
        # complete: every task has a successful record; otherwise a rerun resumes (and retries failures)
        od.write_manifest(COMPLETE if ok == n_tasks else INCOMPLETE, tasks=n_tasks, ok=ok, failed=failed)
    print(md.read_text(), end="")
    console.print(f"{run.computed} task(s) run, {run.skipped} skipped (done), {failed} failed; "
                  f"wall {time.perf_counter() - t0:.1f} s")
    for f in (out / "results.jsonl", md, js):
        console.print(f"wrote {f}")
    if failed:
        raise typer.Exit(1)

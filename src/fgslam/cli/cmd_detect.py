"""``fgslam detect``: rocks from a bag's stereo images, written into a copy of the bag."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


@app.command("detect")
def detect_cmd(
    bag: Path = typer.Argument(..., help="A ROS 2 bag with stereo images, CameraInfo and /tf_static."),
    out: Path = typer.Option(..., "--out", help="The new bag: every message of BAG plus the rock topic."),
    topic: list[str] = typer.Option([], "--topic", help="Map an input role to a topic, ROLE=NAME (repeatable): left_image, right_image, left_info, right_info, tf_static, rocks (the topic written)."),
    config: Path | None = typer.Option(None, "--config", help="YAML with an images: block (pair tolerance, T_base_cam, baseline, front-end) and topics:."),
    restart: bool = typer.Option(False, "--restart", help="Discard the saved frames of an earlier, stopped run instead of resuming it."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT if it exists."),
) -> None:
    """Run the rover detector and stereo triangulation on every stereo pair of BAG and write the
    rocks (vision_msgs/Detection3DArray in base_link) into OUT; a stopped run resumes."""
    import shutil
    import time

    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from fgslam.cli.cmd_run import load_config, topic_map
    from fgslam.errors import InputFileError
    from fgslam.inputs import bag_topics
    from fgslam.io.detect_bag import DetectCheckpoint, write_with_rocks
    from fgslam.io.image_rocks import DetectStats, StereoBag, detect_rocks
    from reloc.config import config_to_dict

    console = Console(stderr=True)
    cfg = load_config(config)
    topics = bag_topics(topic_map(cfg.topics, topic))
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise InputFileError(f"{out} exists; pass --overwrite to replace it")
        if out.resolve() == bag.resolve():
            raise InputFileError(f"--out {out} is the input bag")
    stereo = StereoBag(bag, topics, cfg.images)
    checkpoint = DetectCheckpoint(out, bag, {"images": config_to_dict(cfg.images), "topics": topics.as_roles()},
                                  restart=restart)
    stats = DetectStats()
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, transient=False) as progress:
        task = progress.add_task("detecting rocks (stereo pairs)", total=stereo.n_pairs,
                                 completed=len(checkpoint.frames))
        try:
            for ns, obs in detect_rocks(stereo, after_ns=checkpoint.last_ns, stats=stats):
                checkpoint.add(ns, obs)
                progress.advance(task)
        finally:
            checkpoint.flush()  # a stopped run keeps what it did
    t0 = time.perf_counter()
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    counts = write_with_rocks(bag, out, checkpoint.frames, topics.rocks)
    checkpoint.remove()
    n_rocks = sum(len(o) for _, o in checkpoint.frames)
    console.print(f"{len(checkpoint.frames)} stereo pairs, {n_rocks} rocks on {topics.rocks}; "
                  f"{stats.n_frames} pairs detected now at {stats.frames_per_s:.2f} frames/s "
                  f"(decode {stats.decode_s:.1f} s, detect {stats.detect_s:.1f} s, stereo {stats.stereo_s:.1f} s); "
                  f"bag written in {time.perf_counter() - t0:.1f} s")
    console.print(f"wrote {out} ({sum(counts.values())} messages)")

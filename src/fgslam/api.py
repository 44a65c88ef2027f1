"""The Python facade: a traverse simulated, run and compared in three lines.

    import fgslam
    sim_dir = fgslam.simulate("my2022", "runs/my2022", seed=0, distance_m=20)
    run = fgslam.run(sim_dir, backend="isam2", out="runs/isam2")       # run.metrics["ate"]["rmse"]
    table = fgslam.compare([sim_dir], out="runs/compare")              # one metrics dict per input

Each does what its command does (``fgslam sim``, ``fgslam run``, ``fgslam compare``) with the same
files, without the console: configs are YAML paths, dicts of overrides or config objects;
``out`` None keeps the results in memory only. :func:`run_one` is the step ``fgslam run`` and
:func:`run` share.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["RunOutcome", "compare", "run", "run_one", "simulate"]


@dataclass
class RunOutcome:
    """One back-end's run: its ``key`` (``isam2_reloc``), the :class:`fgslam.runner.RunResult`,
    the ground truth (or None), ``metrics`` (as metrics.json), ``used`` (as config.yaml) and the
    files written (none without ``out``)."""

    key: str
    result: Any
    gt: Any
    metrics: dict
    used: dict
    files: list[Path]


def _compare_config(config):
    from fgslam.compare import CompareConfig
    from fgslam.config_file import compare_overrides, load_compare_config
    from reloc.config import config_from_dict

    if config is None or isinstance(config, CompareConfig):
        return config or CompareConfig()
    if isinstance(config, dict):
        return config_from_dict(CompareConfig, compare_overrides(config))
    return load_compare_config(Path(config))


def run_one(inputs, backend: str, reloc: bool, cfg, topics: dict | None = None, on_progress=None,
            live: Callable | None = None) -> RunOutcome:
    """Run ``backend`` (with online relocalization when ``reloc``) over ``inputs``
    (:class:`fgslam.inputs.RunInputs`) with the :class:`fgslam.compare.CompareConfig` ``cfg``.
    ``live(key, gt)`` -> a :class:`fgslam.runner.RunObserver` told of the run as it goes (a live
    viewer; its ``finish(result)``, if it has one, is called with the result)."""
    from fgslam.backends.registry import backend_config_dict
    from fgslam.compare import run_key, run_metrics
    from fgslam.fix_sources import OnlineFixes
    from fgslam.run_setup import RunSetup
    from reloc.config import config_to_dict

    setup = RunSetup.of(inputs, cfg)  # bounded back-ends on a long traverse (fgslam.long_traverse)
    gt, runner_cfg = setup.gt, setup.runner
    be = setup.backend(backend)
    relocs = setup.relocalizers() if reloc else []
    fixes = OnlineFixes(relocs) if relocs else None
    key = run_key(backend, reloc)
    observer = live(key, gt) if live is not None else None
    res = setup.run(be, fixes, on_progress=on_progress(key) if on_progress is not None else None, observer=observer)
    if observer is not None and hasattr(observer, "finish"):
        observer.finish(res)
    met = run_metrics(res, gt, res.attempts, cfg.rpe_delta_m)
    used = {
        "backend": backend, "relocalization": reloc, "inputs": inputs.source,
        "runner": config_to_dict(runner_cfg), "relocalizer": config_to_dict(cfg.relocalizer),
        "backend_config": backend_config_dict(be),
        "kind_relocalizers": {"+".join(r.kinds): config_to_dict(r.config) for r in relocs if r.kinds != ("rocks",)},
        "topics": dict(topics if topics is not None else cfg.topics), "images": config_to_dict(cfg.images),
        "rpe_delta_m": cfg.rpe_delta_m, "terrain_height": config_to_dict(cfg.terrain_height),
    }
    return RunOutcome(key, res, gt, met, used, [])


def simulate(world: str = "my2021", out: str | Path = "runs/sim", *, seed: int = 0, distance_m: float | None = None,
             config: str | Path | None = None, overwrite: bool = False) -> Path:
    """``fgslam sim``: simulate ``world`` (a yard preset or a Gazebo model directory) and write its
    bag, catalog and world files into ``out``; returns ``out``."""
    from fgslam.cli.cmd_sim import load_sim_config
    from fgslam.io.sim_dir import sim_output_dir, write_sim_dir
    from sim.simulate import simulate as simulate_run
    from sim.tiled.presets import is_tiled

    cfg = load_sim_config(world, seed, distance_m, Path(config) if config is not None else None)
    out = Path(out)
    if is_tiled(cfg.world):
        from sim.tiled.outputs import simulate_to_bag

        with sim_output_dir(out, overwrite) as od:
            simulate_to_bag(cfg, od.staging, overwrite=False)
            od.commit()
        return out
    write_sim_dir(simulate_run(cfg), out, overwrite)
    return out


def run(directory: str | Path | None = None, *, bag: str | Path | None = None, catalog: str | Path | None = None,
        backend: str = "isam2", reloc: bool = True, out: str | Path | None = None, config=None,
        topics: dict[str, str] | None = None, start=None) -> RunOutcome:
    """``fgslam run``: ``backend`` over a ``fgslam sim`` directory or a ``bag`` + ``catalog``;
    ``topics`` maps roles to the bag's topics, ``start`` a :class:`fgslam.inputs.StartSpec`; files
    written into ``out`` when given. Without ``config`` a directory's ``backend.yaml`` is used
    when it has one, as the command does."""
    from fgslam.cli.cmd_run import load_inputs, sim_dir_config, topic_map
    from fgslam.inputs import bag_topics
    from fgslam.io.outdir import OutputDir
    from fgslam.outputs import write_run_outputs

    if config is None and directory is not None:  # the directory's backend.yaml, as `fgslam run DIR`
        config = sim_dir_config(Path(directory), None)
    cfg = _compare_config(config)
    mapping = topic_map(cfg.topics, [f"{k}={v}" for k, v in (topics or {}).items()])
    inputs = load_inputs(Path(directory) if directory is not None else None, Path(bag) if bag else None,
                         Path(catalog) if catalog else None, start, bag_topics(mapping), cfg.images)
    if out is None:
        return run_one(inputs, backend, reloc, cfg, mapping)
    with OutputDir(Path(out), "run") as od:
        outcome = run_one(inputs, backend, reloc, cfg, mapping)
        write_run_outputs(od.staging, outcome.result, outcome.gt, outcome.metrics, outcome.used, outcome.key)
        outcome.files = od.commit()
    return outcome


def compare(directories: list[str | Path], *, out: str | Path | None = None, config=None,
            rrd: bool = True) -> list[dict]:
    """``fgslam compare``: EKF and iSAM2, with and without the same fixes, on each ``fgslam sim``
    directory; returns each input's metrics (as results.json's ``worlds``), files into ``out``.
    Without ``config`` the directories' common ``backend.yaml`` is used, as the command does
    (directories whose ``backend.yaml`` differ are an error there too)."""
    import dataclasses

    from fgslam.cli.cmd_run import compare_dirs_config
    from fgslam.compare import compare_world
    from fgslam.inputs import bag_topics, check_stream, load_sim_dir
    from fgslam.io.outdir import OutputDir
    from fgslam.outputs import write_comparison

    if config is None:  # the directories' backend.yaml, as `fgslam compare DIR...`
        config = compare_dirs_config([Path(d) for d in directories], None)
    cfg = _compare_config(config)
    topics = bag_topics(cfg.topics)
    inputs_list = [load_sim_dir(Path(d), topics=topics, images=cfg.images) for d in directories]
    comparisons = []
    for inputs in inputs_list:
        runner = check_stream(inputs, cfg.runner)
        comparisons.append(compare_world(inputs, cfg if runner == cfg.runner else dataclasses.replace(cfg, runner=runner)))
    if out is not None:
        with OutputDir(Path(out), "compare") as od:
            write_comparison(od.staging, comparisons, cfg, rrd=rrd)
            od.commit()
    return [wc.metrics for wc in comparisons]

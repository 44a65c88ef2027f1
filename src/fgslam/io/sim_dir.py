"""Write a ``fgslam sim`` output directory (bag/, catalog.csv, rocks_true.csv, world.yaml,
orbital.png), the input that ``fgslam compare`` and :func:`fgslam.inputs.load_sim_dir` read.

The directory is written whole (:mod:`fgslam.io.outdir`): staged, then committed with its
manifest, so a reader never takes a half-written bag for a traverse. An earlier output in it
(a simulated or a recorded bag, a catalog) is only replaced when asked (``overwrite``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from fgslam.io.outdir import OutputDir


def sim_output_dir(out: Path, overwrite: bool = False) -> OutputDir:
    """The :class:`OutputDir` of a simulator run (enter it before simulating: the path is checked
    and locked at once); ``overwrite`` False refuses a directory that already holds a bag or a
    catalog."""
    return OutputDir(out, "sim", replace=overwrite, replace_hint="pass --overwrite to replace them")


def write_sim_files(run, directory: Path):
    """Write the files of ``run`` (:class:`sim.SimRun`) into the (staging) ``directory``; returns
    the bag summary (messages, bytes)."""
    from fgslam.io.catalog_csv import write_catalog_csv
    from sim.bag_writer import write_bag
    from sim.outputs import write_outputs

    directory = Path(directory)
    summary = write_bag(directory / "bag", run.measurements)
    write_outputs(run, directory, catalog=False)
    write_catalog_csv(directory / "catalog.csv", run.catalog)
    return summary


def write_sim_dir(run, out: Path, overwrite: bool = False):
    """Write the simulator run ``run`` into ``out`` (staged, committed with its manifest); returns
    the bag summary. ``overwrite`` False refuses to replace an earlier output there."""
    with sim_output_dir(out, overwrite) as od:
        summary = write_sim_files(run, od.staging)
        od.commit()
    return dataclasses.replace(summary, path=od.path / "bag")

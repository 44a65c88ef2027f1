"""Write a ``fgslam sim`` output directory (bag/, catalog.csv, rocks_true.csv, world.yaml,
orbital.png), the input that ``fgslam compare`` and :func:`fgslam.inputs.load_sim_dir` read."""

from __future__ import annotations

from pathlib import Path


def write_sim_dir(run, out: Path, overwrite: bool = True):
    """Write the simulator run ``run`` (:class:`sim.SimRun`) into ``out``; returns the bag summary
    (messages, bytes). ``overwrite`` False refuses to replace an existing bag."""
    from fgslam.io.catalog_csv import write_catalog_csv
    from sim.bag_writer import write_bag
    from sim.outputs import write_outputs

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = write_bag(out / "bag", run.measurements, overwrite=overwrite)
    write_outputs(run, out, catalog=False)
    write_catalog_csv(out / "catalog.csv", run.catalog)
    return summary

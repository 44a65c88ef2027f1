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


def sim_output_dir(out: Path, overwrite: bool = False, force: bool = False) -> OutputDir:
    """The :class:`OutputDir` of a simulator run (enter it before simulating: the path is checked
    and locked at once); ``overwrite`` False refuses a directory that already holds a bag or a
    catalog; ``force`` writes into a non-empty directory without a manifest."""
    return OutputDir(out, "sim", replace=overwrite, replace_hint="pass --overwrite to replace them", force=force)


def write_sim_files(run, directory: Path, style=None, topics=None, frames=None, image_width_px: int = 640,
                    rock_topic: bool = True):
    """Write the files of ``run`` (:class:`sim.SimRun`) into the (staging) ``directory``; returns
    the bag summary (messages, bytes). ``style``/``topics``: the bag's
    :class:`sim.bag_scene.BagStyle` and names (default: fgslam's, no /tf); ``frames``: the rendered
    stereo pairs (:class:`reloc.camera_bag.StereoFrame`, of a camera ``image_width_px`` wide) to
    write as images with their CameraInfo and mounting; ``rock_topic`` False leaves the rock
    detections out (the images are then the rocks' only input, as on a rover)."""
    from fgslam.io.catalog_csv import write_catalog_csv
    from reloc.measurements import RockObservations, sort_key
    from sim.bag_scene import BagScene, bag_description, stereo_scene
    from sim.bag_writer import write_bag
    from sim.outputs import write_outputs

    directory = Path(directory)
    measurements = [m for m in run.measurements if rock_topic or not isinstance(m, RockObservations)]
    T0 = run.ground_truth.T_world_base[0]
    if frames:
        scene = stereo_scene(run.config.sensors.stereo, image_width_px, T0, run.catalog)
        order = {id(f): i for i, f in enumerate(frames)}
        measurements = sorted(measurements + list(frames),
                              key=lambda m: (m.t, 99, order[id(m)]) if id(m) in order else (*sort_key(m), 0))
    else:
        scene = BagScene(T_world_odom=T0, catalog_xy_m=run.catalog.xy_m[:, :2], catalog_size_m=run.catalog.size_m)
    summary = write_bag(directory / "bag", measurements, topics=topics, style=style, scene=scene,
                        custom_data={"fgslam.catalog": "catalog.csv"})
    write_outputs(run, directory, catalog=False, bag=bag_description(style, topics, images=bool(frames)))
    write_catalog_csv(directory / "catalog.csv", run.catalog)
    return summary


def write_sim_dir(run, out: Path, overwrite: bool = False):
    """Write the simulator run ``run`` into ``out`` (staged, committed with its manifest); returns
    the bag summary. ``overwrite`` False refuses to replace an earlier output there."""
    with sim_output_dir(out, overwrite) as od:
        summary = write_sim_files(run, od.staging)
        od.commit()
    return dataclasses.replace(summary, path=od.path / "bag")

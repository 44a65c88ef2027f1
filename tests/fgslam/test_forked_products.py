"""The demo's overlap: a kilometre run's orbital products written on a forked process while the
bag is read back (fgslam.lifetime.Forked, simulate_to_bag's write_products, load_bag's preread)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from fgslam.errors import InputFileError
from fgslam.inputs import load_sim_dir, read_bag_measurements
from fgslam.lifetime import Forked, ForkedTaskError
from sim.tiled.outputs import simulate_to_bag
from sim.tiled.presets import preset_config


def _fail():
    raise ValueError("bad tile")


def test_a_forked_task_gives_its_result_or_names_its_failure():
    big = np.arange(10)
    assert Forked(lambda: {"sum": int(big.sum())}, "adding").result() == {"sum": 45}  # a closure, not pickled
    with pytest.raises(ForkedTaskError, match=r"writing failed: ValueError: bad tile"):
        Forked(_fail, "writing").result()
    with pytest.raises(ForkedTaskError, match=r"dying: its process died \(exit code 3\)"):
        Forked(lambda: os._exit(3), "dying").result()
    slow = Forked(lambda: time.sleep(60), "sleeping")
    t0 = time.perf_counter()
    slow.kill()
    assert not slow._proc.is_alive() and time.perf_counter() - t0 < 5.0


def test_products_written_beside_the_bag_read_are_the_products_written_after_it(tmp_path):
    cfg = preset_config("rocky-1km", 3, {"traverse": {"distance_m": 5.0}, "tiled": {
        "size_m": 512.0, "orbital": {"write_image": False, "corridor_m": 20.0}}})
    simulate_to_bag(cfg, tmp_path / "after")
    read = {}

    def beside(write):
        job = Forked(write, "writing the orbital products")
        read["bag"] = read_bag_measurements(tmp_path / "beside" / "bag")
        return job.result()

    run = simulate_to_bag(cfg, tmp_path / "beside", write_products=beside)
    assert run.products.counts["catalog"] > 0 and run.stats["n_catalog"] == run.products.counts["catalog"]
    for name in ("catalog.csv", "catalog_truth.csv", "craters.csv", "rocks_true.csv", "dem.tif", "backend.yaml"):
        assert (tmp_path / "beside" / name).read_bytes() == (tmp_path / "after" / name).read_bytes(), name
    got, ref = load_sim_dir(tmp_path / "beside", preread=read["bag"]), load_sim_dir(tmp_path / "after")
    assert got.measurements is read["bag"].measurements and len(got.measurements) == len(ref.measurements)
    assert [type(m) for m in got.measurements] == [type(m) for m in ref.measurements]
    assert len(got.catalogs["rocks"]) == len(ref.catalogs["rocks"])
    with pytest.raises(InputFileError, match="read from another bag"):
        load_sim_dir(tmp_path / "after", preread=read["bag"])

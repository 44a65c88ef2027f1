"""A simulator run fed in memory and the same run read back from its `fgslam sim` directory are
the same inputs: same measurements and the same start pose and covariance (the demo and
`fgslam compare` on one world then agree)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fgslam.inputs import from_sim_run, load_sim_dir
from fgslam.io.outdir import OutputDirError, read_manifest
from fgslam.io.sim_dir import write_sim_dir
from reloc.backend import known_start_cov
from reloc.measurements import RockObservations
from sim.config import SimConfig, TraverseConfig
from sim.simulate import simulate


def test_run_in_memory_and_its_directory_are_the_same_inputs(tmp_path):
    run = simulate(SimConfig(world="cnes", seed=2, traverse=TraverseConfig(distance_m=4.0)))
    write_sim_dir(run, tmp_path / "run")
    a, b = from_sim_run(run), load_sim_dir(tmp_path / "run")
    np.testing.assert_array_equal(a.initial.cov, b.initial.cov)
    np.testing.assert_array_equal(a.initial.cov, known_start_cov())
    np.testing.assert_allclose(a.initial.T_world_base, b.initial.T_world_base, atol=1e-12)
    assert a.initial.t == b.initial.t
    assert [type(m) for m in a.measurements] == [type(m) for m in b.measurements]
    ta, tb = np.array([m.t for m in a.measurements]), np.array([m.t for m in b.measurements])
    np.testing.assert_allclose(ta, tb, atol=1e-9)  # nanosecond stamps in the bag
    ra = [m for m in a.measurements if isinstance(m, RockObservations)]
    rb = [m for m in b.measurements if isinstance(m, RockObservations)]
    assert sum(len(m) for m in ra) > 0
    for x, y in zip(ra, rb):
        np.testing.assert_array_equal(x.xyz_base_m, y.xyz_base_m)
        np.testing.assert_array_equal(x.cov_base_m2, y.cov_base_m2)
    # written whole, and not replaced unless asked (issue 17, case 4)
    manifest = read_manifest(tmp_path / "run")
    assert manifest["kind"] == "sim" and manifest["status"] == "complete"
    assert {"bag/metadata.yaml", "catalog.csv", "world.yaml", "orbital.png", "rocks_true.csv"} <= set(manifest["files"])
    with pytest.raises(OutputDirError, match="already holds bag"):
        write_sim_dir(run, tmp_path / "run")
    summary = write_sim_dir(run, tmp_path / "run", overwrite=True)
    assert summary.path == tmp_path / "run" / "bag" and read_manifest(tmp_path / "run")["files"] == manifest["files"]
    # a directory whose writing was interrupted is not read as a traverse
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({**manifest, "status": "writing"}))
    with pytest.raises(OutputDirError, match="incomplete `fgslam sim` output"):
        load_sim_dir(tmp_path / "run")

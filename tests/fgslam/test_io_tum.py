"""TUM trajectories: round trip, evo reads our files with the same poses, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fgslam.errors import InputFileError
from fgslam.io import read_tum, write_tum


def _poses(rng, k=50):
    t = np.cumsum(rng.uniform(0.01, 0.1, k)) + 1.7e9  # epoch-like stamps keep sub-us precision
    T = np.tile(np.eye(4), (k, 1, 1))
    T[:, :3, :3] = Rotation.random(k, random_state=1).as_matrix()
    T[:, :3, 3] = rng.normal(0, 30, (k, 3))
    return t, T


def test_round_trip(tmp_path, rng):
    t, T = _poses(rng)
    path = tmp_path / "traj.tum"
    write_tum(path, t, T)
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.t, t)
    np.testing.assert_allclose(traj.T_world_base, T, atol=1e-12)


def test_evo_reads_the_same_poses(tmp_path, rng):
    from evo.tools import file_interface

    t, T = _poses(rng)
    path = tmp_path / "traj.tum"
    write_tum(path, t, T)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(evo_traj.timestamps, t)
    np.testing.assert_allclose(np.asarray(evo_traj.poses_se3), T, atol=1e-12)
    # And the other way: a file evo writes reads back into the same poses.
    evo_path = tmp_path / "evo.tum"
    file_interface.write_tum_trajectory_file(str(evo_path), evo_traj)
    np.testing.assert_allclose(read_tum(evo_path).T_world_base, T, atol=1e-9)


def test_write_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_tum(tmp_path / "a", np.zeros(2), np.tile(np.eye(4), (3, 1, 1)))
    bad = np.tile(np.eye(4), (1, 1, 1))
    bad[0, 0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        write_tum(tmp_path / "a", np.zeros(1), bad)


@pytest.mark.parametrize(
    "text, needle",
    [
        ("# only a comment\n", "no poses"),
        ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", "line 2: 7 field(s)"),
        ("0 1 2 x 0 0 0 1\n", "line 1: non-numeric"),
        ("0 1 nan 3 0 0 0 1\n", "line 1: NaN or inf"),
        ("0 1 2 3 0 0 0 2\n", "line 1: quaternion norm 2.000000"),
    ],
)
def test_malformed_files(tmp_path, text, needle):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(InputFileError) as exc:
        read_tum(path)
    assert str(path) in str(exc.value) and needle in str(exc.value)

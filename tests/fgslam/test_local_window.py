"""The relocalizer's local map window (fgslam.local_window) and the sparse-ground radius."""

from __future__ import annotations

import numpy as np

from fgslam.local_window import LocalMapWindow, rigid_2d
from fgslam.match_to_fix import select_local_map
from fgslam.relocalizer_config import RelocalizerConfig
from reloc.backend import LandmarkMap


def _map(ids, xy) -> LandmarkMap:
    xy = np.asarray(xy, float).reshape(-1, 2)
    n = len(xy)
    return LandmarkMap(np.asarray(ids, int), np.column_stack([xy, np.zeros(n)]), np.tile(np.eye(3) * 0.01, (n, 1, 1)),
                       np.full(n, 0.5), np.full(n, 3), "rocks")


def test_rigid_2d_recovers_a_rotation_and_translation():
    rng = np.random.default_rng(1)
    src = rng.uniform(-10, 10, (6, 2))
    a = 0.3
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    Re, te = rigid_2d(src, src @ R.T + [1.0, -2.0])
    assert np.allclose(Re, R) and np.allclose(te, [1.0, -2.0])
    assert np.allclose(rigid_2d(src[:1], src[:1] + 3.0)[1], 3.0)


def test_dropped_landmarks_are_kept_along_the_path_in_the_back_ends_frame():
    w = LocalMapWindow(path_m=20.0, max_kept=100)
    # the rover drives along x; the back-end holds only the landmarks within 5 m behind it
    rocks = {i: np.array([2.0 * i, 1.0]) for i in range(40)}
    shift = np.zeros(2)
    for step in range(30):
        x = float(step)
        if step == 15:  # a fix moves the back-end's frame by 0.5 m: held and dropped move alike
            shift = np.array([0.5, -0.2])
        ids = [i for i, p in rocks.items() if x - 5.0 <= p[0] <= x + 5.0]
        out = w.update(_map(ids, [rocks[i] + shift for i in ids]), np.array([x, 0.0]) + shift)
        assert set(ids) <= set(out.ids.tolist())
    kept = {int(i): out.xyz_world_m[r, :2] for r, i in enumerate(out.ids) if i not in ids}
    assert kept, "dropped landmarks are kept"
    for i, xy in kept.items():
        assert np.allclose(xy, rocks[i] + shift, atol=1e-9)  # in the back-end's current frame
        assert rocks[i][0] >= 29.0 - 5.0 - 20.0 - 1.0  # last seen within the path window
    assert min(kept) > 0  # the start of the route has left the window
    small = LocalMapWindow(path_m=1000.0, max_kept=3)
    for step in range(30):
        ids = [i for i, p in rocks.items() if step - 5.0 <= p[0] <= step + 5.0]
        small.update(_map(ids, [rocks[i] for i in ids]), np.array([float(step), 0.0]))
    assert len(small) == 3 and small.n_kept_max == 3


def test_sparse_ground_widens_the_local_map():
    xy = [[1.0, 0.0], [2.0, 1.0], [50.0, 0.0], [60.0, 5.0], [100.0, 0.0]]
    lmap = _map(range(5), xy)
    wide = select_local_map(lmap, np.zeros(2), RelocalizerConfig(sparse_below=5, sparse_radius_m=80.0))
    assert wide.tolist() == [0, 1, 2, 3]
    narrow = select_local_map(lmap, np.zeros(2), RelocalizerConfig(sparse_below=2))
    assert narrow.tolist() == [0, 1]

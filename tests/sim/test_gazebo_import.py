"""Gazebo-world importer on the ERC Mars-yard assets, and its errors on malformed input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from sim.errors import WorldImportError
from sim.gazebo_import import import_gazebo_world, read_obj, split_components


def _raw_obj_vertices(path: Path) -> np.ndarray:
    """Independent reading of the OBJ vertex lines."""
    rows = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return np.array(rows, dtype=float)


@pytest.fixture(scope="module")
def my2021(erc_dir):
    return import_gazebo_world(erc_dir / "marsyard2021")


def test_terrain_matches_the_geotiff(my2021, erc_dir):
    import tifffile

    raw = tifffile.imread(erc_dir / "marsyard2021/dem/marsyard_terrain_hm.tif").astype(float)
    assert my2021.extent == pytest.approx((-23.5, 23.5, -23.5, 23.5))
    n = raw.shape[0]
    # image row 0 is the +y edge, column 0 the -x edge
    xy = np.array([[-23.5, 23.5], [23.5, 23.5], [-23.5, -23.5], [0.0, 0.0]])
    expected = [raw[0, 0], raw[0, -1], raw[-1, 0], raw[(n - 1) // 2, (n - 1) // 2]]
    got = my2021.height_at(xy)
    np.testing.assert_allclose(got[:3], expected[:3], atol=1e-6)
    assert got[3] == pytest.approx(expected[3], abs=0.1)


def test_39_big_rocks_at_their_mesh_positions(my2021, erc_dir):
    rocks = my2021.rocks
    assert len(rocks) == 39
    raw = _raw_obj_vertices(erc_dir / "marsyard2021/meshes/rocks_big.obj")
    # the mesh link is rotated +90 deg about z in model.sdf: (x, y) -> (-y, x)
    placed = np.column_stack([-raw[:, 1], raw[:, 0], raw[:, 2]])
    assert len(rocks.vertices_m) == len(placed)
    # every placed vertex belongs to exactly one imported rock, whose box centre is the rock position
    from scipy.spatial import cKDTree

    assert cKDTree(placed).query(rocks.vertices_m)[0].max() < 1e-6
    assert cKDTree(rocks.vertices_m).query(placed)[0].max() < 1e-6
    for k in range(len(rocks)):
        v = rocks.vertices_m[np.unique(rocks.triangles[rocks.triangle_rock == k])]
        np.testing.assert_allclose(rocks.xyz_m[k], 0.5 * (v.min(axis=0) + v.max(axis=0)), atol=1e-9)
        assert 0.2 < rocks.size_m[k] < 2.0
    # the rocks are separate bodies
    d = np.linalg.norm(rocks.xyz_m[:, None, :2] - rocks.xyz_m[None, :, :2], axis=2) + np.eye(len(rocks)) * 99
    assert d.min() > 0.3


def test_big_rocks_rest_on_the_imported_terrain(my2021):
    rocks = my2021.rocks
    gaps = []
    for k in range(len(rocks)):
        v = rocks.vertices_m[np.unique(rocks.triangles[rocks.triangle_rock == k])]
        low = v[np.argmin(v[:, 2])]
        gaps.append(low[2] - my2021.height_at(low[None, :2])[0])
        assert np.max(v[:, 2] - my2021.height_at(v[:, :2])) > 0.05  # it sticks out of the ground
    gaps = np.array(gaps)
    assert np.all(np.abs(gaps) < 0.35), gaps
    assert -0.25 < np.median(gaps) < 0.0  # slightly embedded, as in the Gazebo world


def test_png_heightmap_agrees_with_geotiff(erc_dir, tmp_path):
    # the PNG shipped with the assets is the MY2022 heightmap (identical file in both yards)
    src = erc_dir / "marsyard2022"
    tif_world = import_gazebo_world(src)
    assert len(tif_world.rocks) == 0 and tif_world.extent == pytest.approx((-25, 25, -25, 25))
    (tmp_path / "dem").mkdir()
    shutil.copy(src / "dem/marsyard2022_terrain_hm.png", tmp_path / "dem/hm.png")
    sdf = (src / "model.sdf").read_text().replace("dem/marsyard2022_terrain_hm.tif", "dem/hm.png")
    (tmp_path / "model.sdf").write_text(sdf)
    png_world = import_gazebo_world(tmp_path)
    xy = np.random.default_rng(0).uniform(-24, 24, (400, 2))
    a, b = png_world.height_at(xy), tif_world.height_at(xy)
    assert np.corrcoef(a, b)[0, 1] > 0.99
    assert np.median(np.abs(a - b)) < 0.05  # 8-bit PNG scaled to <size> z = 4.82 m
    assert np.ptp(png_world.terrain.z_m) == pytest.approx(4.82, abs=0.05)


def test_components_of_a_two_part_mesh():
    tet = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    v = np.vstack([np.eye(3, 3, 0).tolist() + [[0, 0, 0]], (np.eye(3) + 5).tolist() + [[5, 5, 5]]])
    parts = split_components(v, np.vstack([tet, tet + 4]))
    assert len(parts) == 2
    assert sorted(p[0][:, 0].max() for p in parts) == [1.0, 6.0]


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda s: s.replace("<model", "<broken").replace("</model>", "</broken>"), "no <model>"),
        (lambda s: s.replace("<size>47 47 6.57519871597</size>", "<size>47 x 6</size>"), "not numeric"),
        (lambda s: s.replace("<size>47 47 6.57519871597</size>", "<size>47 47</size>"), "needs 3 numbers"),
        (lambda s: s.replace("</sdf>", ""), "not valid XML"),
        (lambda s: s.replace("marsyard_terrain_hm.tif", "missing.tif"), "heightmap file not found"),
    ],
)
def test_malformed_model_raises(erc_dir, tmp_path, mutate, match):
    src = erc_dir / "marsyard2021"
    shutil.copytree(src / "dem", tmp_path / "dem")
    (tmp_path / "model.sdf").write_text(mutate((src / "model.sdf").read_text()))
    with pytest.raises(WorldImportError, match=match):
        import_gazebo_world(tmp_path)


def test_missing_model_and_bad_obj_raise(tmp_path):
    with pytest.raises(WorldImportError, match="no model.sdf"):
        import_gazebo_world(tmp_path)
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 7\n")
    with pytest.raises(WorldImportError, match="outside"):
        read_obj(bad)
    bad.write_text("v 0 zero 0\n")
    with pytest.raises(WorldImportError, match="bad vertex"):
        read_obj(bad)


def test_an_imported_world_can_be_driven(erc_dir):
    from sim.config import SimConfig, TraverseConfig
    from sim.simulate import simulate

    run = simulate(SimConfig(world=str(erc_dir / "marsyard2021"), seed=0, traverse=TraverseConfig(distance_m=5.0)))
    assert run.world.source.endswith("marsyard2021") and len(run.rocks_true) == 39
    assert run.stats["distance_m"] > 4.5
    p = run.ground_truth.positions_m
    ground = run.world.height_at(p[:, :2])
    assert np.all(np.abs(p[:, 2] - ground - run.config.rover.base_height_m) < 0.15)

"""Triangle descriptors and the geometric hash: invariance, handedness, degeneracy, look-up."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reloc.descriptors import label_triangles, triangle_invariants
from reloc.hashing import TriangleHash

coord = st.floats(-20.0, 20.0, allow_nan=False)


def _well_shaped(p: np.ndarray) -> bool:
    inv = triangle_invariants(p[None])
    sides = np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1)
    # well away from degenerate and from ties between sides (labels would be ambiguous)
    s = np.sort(sides)
    return bool(inv.norm_area[0] > 0.2 and s[0] > 0.5 and np.min(np.diff(s)) > 1e-3 * s[2])


@settings(max_examples=150, deadline=None)
@given(
    pts=st.lists(st.tuples(coord, coord), min_size=3, max_size=3),
    theta=st.floats(-np.pi, np.pi),
    scale=st.floats(0.2, 5.0),
    shift=st.tuples(coord, coord),
    perm=st.permutations([0, 1, 2]),
)
def test_invariants_unchanged_by_rotation_scale_translation_and_order(pts, theta, scale, shift, perm):
    p = np.array(pts, float)
    if not _well_shaped(p):
        return
    c, s = np.cos(theta), np.sin(theta)
    q = scale * p @ np.array([[c, -s], [s, c]]).T + np.array(shift)
    q = q[list(perm)]
    a, b = triangle_invariants(p[None]), triangle_invariants(q[None])
    np.testing.assert_allclose(b.ratios, a.ratios, atol=1e-9)
    np.testing.assert_allclose(b.angles_rad, a.angles_rad, atol=1e-7)
    np.testing.assert_allclose(b.norm_area, a.norm_area, atol=1e-9)
    assert b.handedness[0] == a.handedness[0]
    assert np.isclose(a.angles_rad.sum(), np.pi)


@settings(max_examples=80, deadline=None)
@given(pts=st.lists(st.tuples(coord, coord), min_size=3, max_size=3))
def test_mirror_image_flips_handedness_only(pts):
    p = np.array(pts, float)
    if not _well_shaped(p):
        return
    m = p * np.array([-1.0, 1.0])
    a, b = triangle_invariants(p[None]), triangle_invariants(m[None])
    np.testing.assert_allclose(b.ratios, a.ratios, atol=1e-9)
    assert b.handedness[0] == -a.handedness[0]


def test_labels_face_their_sides_and_sides_are_sorted():
    xy = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]])
    lab = label_triangles(xy, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(lab.sides_m[0], [3.0, 4.0, 5.0])
    v = lab.vertices[0]
    for i, side in enumerate(lab.sides_m[0]):
        others = [j for j in v if j != v[i]]
        assert np.isclose(np.linalg.norm(xy[others[0]] - xy[others[1]]), side)
    # the right angle faces the longest side: vertex 2 of the labelling is the origin
    assert v[2] == 0


def test_degenerate_triangles_are_excluded():
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.001], [0.0, 0.05], [0.0, 1.0]])
    lab = label_triangles(xy, np.array([[0, 1, 2], [0, 3, 4], [0, 1, 4]]), min_side_m=0.25, min_shape=0.12)
    assert lab.keep.tolist() == [False, False, True]  # collinear, near-duplicate, fine


def test_hash_finds_triangles_within_tolerance_and_respects_handedness():
    rng = np.random.default_rng(3)
    sides = np.sort(rng.uniform(0.5, 5.0, (5000, 3)), axis=1).astype(np.float32)
    hand = rng.choice([-1, 1], 5000).astype(np.int8)
    table, order = TriangleHash.build(sides, hand, bin_m=0.1)
    rows_sorted = sides[order]
    hand_sorted = hand[order]
    query = sides[:50] + rng.uniform(-0.05, 0.05, (50, 3)).astype(np.float32)
    qi, pos = table.query(query, hand[:50], 0.06)
    for i in range(50):
        hits = pos[qi == i]
        # every triangle of equal handedness within the tolerance is among the candidates ...
        close = np.flatnonzero(np.all(np.abs(sides - query[i]) <= 0.06, axis=1) & (hand == hand[i]))
        assert set(np.flatnonzero(np.isin(order, close))) <= set(hits.tolist())
        # ... and every candidate has the same handedness and lies in a touched bin
        assert np.all(hand_sorted[hits] == hand[i])
        assert np.all(np.abs(rows_sorted[hits] - query[i]) <= 0.06 + 0.1 + 1e-6)


def test_hash_rejects_non_positive_bins():
    with pytest.raises(ValueError):
        TriangleHash.build(np.ones((1, 3)), np.ones(1), 0.0)

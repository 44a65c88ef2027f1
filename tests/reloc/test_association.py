"""Data association and the stereo point model shared by both back-ends."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from reloc.association import AssociationConfig, associate
from reloc.errors import MeasurementError
from reloc.landmark_book import LandmarkBook, LandmarkBookConfig
from reloc.landmark_model import point_in_base, point_to_world


def frame(rng, L, idx, R, p, sigma=0.05):
    z = point_in_base(R, p, L[idx]) + rng.normal(0, sigma, (len(idx), 3))
    return z, np.tile(np.eye(3) * sigma**2, (len(idx), 1, 1))


def test_recovers_a_shuffled_subset(rng):
    L = rng.uniform(-8, 8, (40, 3))
    L[:, 2] = rng.uniform(-0.5, 0.5, 40)
    R = Rotation.from_euler("z", 0.7).as_matrix()
    p = np.array([1.0, -2.0, 0.1])
    idx = rng.permutation(40)[:15]
    z, Rz = frame(rng, L, idx, R=R, p=p)
    zhat = point_in_base(R, p, L)
    S = np.tile(np.eye(3) * 0.01**2, (40, 1, 1))
    a = associate(z, Rz, zhat, S, AssociationConfig(max_range_m=100.0))
    assert np.array_equal(a.landmark_of, idx)
    assert not a.is_new.any() and a.n_ambiguous == 0
    assert np.all(a.d2 < 11.345)


def test_two_close_rocks_are_not_both_given_one_landmark(rng):
    # two detections between two landmarks 0.3 m apart: nearest neighbour alone would give both to
    # landmark 0; the assignment keeps them one-to-one
    L = np.array([[3.0, 0.0, 0.0], [3.3, 0.0, 0.0]])
    z = np.array([[3.12, 0.0, 0.0], [3.24, 0.0, 0.0]])
    Rz = np.tile(np.eye(3) * 0.1**2, (2, 1, 1))
    a = associate(z, Rz, L, np.zeros((2, 3, 3)))
    assert sorted(a.landmark_of.tolist()) == [0, 1]
    assert a.landmark_of.tolist() == [0, 1]  # the cheaper total assignment


def test_new_ambiguous_and_out_of_range(rng):
    L = np.array([[3.0, 0.0, 0.0]])
    Rz = np.tile(np.eye(3) * 0.1**2, (4, 1, 1))
    z = np.array([
        [3.02, 0.0, 0.0],  # associated
        [3.0, 0.39, 0.0],  # d2 = 0.39^2 / 0.01 = 15.2: between the gates -> ambiguous
        [6.0, 2.0, 0.0],  # far from everything -> new
        [20.0, 0.0, 0.0],  # beyond max_range_m
    ])
    a = associate(z, Rz, L, np.zeros((1, 3, 3)))
    assert a.landmark_of.tolist() == [0, -1, -1, -1]
    assert a.is_new.tolist() == [False, False, True, False]
    assert a.n_ambiguous == 1 and a.n_out_of_range == 1
    assert np.isinf(a.d2[1:]).all()


def test_duplicate_new_detections_initialise_once():
    z = np.array([[5.0, 1.0, 0.0], [5.05, 1.0, 0.0], [7.0, -3.0, 0.0]])
    Rz = np.tile(np.eye(3) * 0.1**2, (3, 1, 1))
    a = associate(z, Rz, np.zeros((0, 3)), np.zeros((0, 3, 3)))
    assert a.is_new.tolist() == [True, False, True]


def test_size_veto():
    L = np.array([[3.0, 0.0, 0.0]])
    z = np.array([[3.0, 0.0, 0.0]])
    Rz = np.eye(3)[None] * 0.01
    a = associate(z, Rz, L, np.zeros((1, 3, 3)), size_z=np.array([1.2]), size_hat=np.array([0.2]))
    assert a.landmark_of.tolist() == [-1] and not a.is_new[0]
    a = associate(z, Rz, L, np.zeros((1, 3, 3)), size_z=np.array([0.25]), size_hat=np.array([0.2]))
    assert a.landmark_of.tolist() == [0]


def test_joint_compatibility_drops_the_inconsistent_pair(rng):
    # every pair passes its own gate, but together they are not compatible with one rigid pose
    # error: with a joint covariance in which the shared pose error dominates, the pair that
    # disagrees with the others is dropped
    L = np.array([[3.0, -1.0, 0.0], [4.0, 1.0, 0.0], [5.0, 0.0, 0.0]])
    shift = np.array([0.25, 0.0, 0.0])
    z = L + shift
    z[2] = L[2] - shift  # moved the other way
    Rz = np.tile(np.eye(3) * 0.02**2, (3, 1, 1))
    S_pose = np.eye(3) * 0.2**2  # common translation uncertainty
    S_hat = np.tile(S_pose, (3, 1, 1))

    def joint_cov(det, cand):
        k = len(det)
        S = np.kron(np.ones((k, k)), S_pose)
        for i in range(k):
            S[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += Rz[det[i]]
        return S

    a = associate(z, Rz, L, S_hat)
    assert a.landmark_of.tolist() == [0, 1, 2]  # block-diagonal check sees nothing wrong
    a = associate(z, Rz, L, S_hat, AssociationConfig(min_pairs_uncertain=1), joint_cov=joint_cov)
    assert a.n_jc_dropped == 1 and a.landmark_of.tolist() == [0, 1, -1]
    # by default the two pairs left are too few for a prediction 10 sigma wider than the detections
    a = associate(z, Rz, L, S_hat, joint_cov=joint_cov)
    assert a.n_jc_dropped == 1 and a.n_uncertain_dropped == 2 and a.landmark_of.tolist() == [-1, -1, -1]


def test_bad_shapes_and_nan_are_named():
    with pytest.raises(MeasurementError, match="R_z"):
        associate(np.zeros((2, 3)), np.zeros((3, 3, 3)), np.zeros((1, 3)), np.zeros((1, 3, 3)))
    with pytest.raises(MeasurementError, match="zhat_base contains NaN"):
        associate(np.ones((1, 3)), np.eye(3)[None], np.full((1, 3), np.nan), np.zeros((1, 3, 3)))


@settings(max_examples=40, deadline=None)
@given(st.floats(-3.1, 3.1), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-20, 20), st.floats(-20, 20))
def test_point_model_round_trip(yaw, pitch, roll, x, y):
    R = Rotation.from_euler("zyx", [yaw, pitch, roll]).as_matrix()
    p = np.array([x, y, 0.5])
    z = np.array([[2.0, 0.5, -0.3], [7.0, -2.0, 0.1]])
    cov = np.stack([np.diag([0.1, 0.02, 0.03]), np.diag([0.5, 0.05, 0.05])])
    l, c = point_to_world(R, p, z, cov)
    assert np.allclose(point_in_base(R, p, l), z, atol=1e-9)
    assert np.allclose(np.linalg.eigvalsh(c), np.linalg.eigvalsh(cov), atol=1e-12)


def test_landmark_book_confirm_drop_evict():
    book = LandmarkBook(LandmarkBookConfig(confirm_n_obs=3, confirm_window_s=2.0))
    ids = book.add(0.0, np.array([0.3, 0.4, 0.5]))
    assert ids.tolist() == [0, 1, 2] and not book.confirmed.any()
    book.observe(np.array([0, 1]), 1.0, np.array([0.3, 0.5]))
    book.observe(np.array([0]), 1.5, np.array([0.3]))
    assert book.confirmed.tolist() == [True, False, False]
    assert book.stale(1.9).tolist() == [False, False, False]
    assert book.stale(2.5).tolist() == [False, True, True]
    book.observe(np.array([1]), 3.0, np.array([0.4]))  # third sighting too late
    assert not book.confirmed[1]
    book.keep(np.array([True, True, False]))
    assert book.ids.tolist() == [0, 1] and np.allclose(book.size_m, [0.3, 1.3 / 3])
    ev = book.evictions(1, distance_m=np.array([5.0, 1.0]))
    assert ev.tolist() == [True, False]  # seen least recently
    ev = book.evictions(1, distance_m=np.array([5.0, 1.0]), protect=np.array([True, False]))
    assert ev.tolist() == [False, True]
    assert book.copy().ids is not book.ids


def _brute_force_drop_order(nu, S, limit_of_k):
    """Reference: drop, one at a time, the pair whose removal leaves the smallest joint distance."""
    idx = list(range(len(nu) // 3))
    dropped = []
    while idx:
        cols = np.concatenate([np.arange(3 * i, 3 * i + 3) for i in idx])
        d2 = nu[cols] @ np.linalg.solve(S[np.ix_(cols, cols)], nu[cols])
        if d2 <= limit_of_k(len(idx)):
            break
        best = min(idx, key=lambda i: (lambda c: nu[c] @ np.linalg.solve(S[np.ix_(c, c)], nu[c]))(
            np.concatenate([np.arange(3 * j, 3 * j + 3) for j in idx if j != i])) if len(idx) > 1 else 0.0)
        idx.remove(best)
        dropped.append(best)
    return idx, dropped


def test_joint_compatibility_drops_the_same_pairs_as_the_brute_force_search():
    from scipy.stats import chi2

    from reloc.association import _joint_compatible

    rng = np.random.default_rng(5)
    cfg = AssociationConfig()
    for trial in range(30):  # up to 40 pairs: many downdates in place, and fresh inverses between them
        k = int(rng.integers(2, 12 if trial < 20 else 40))
        A = rng.normal(size=(3 * k, 3 * k)) * 0.05
        S = A @ A.T + np.eye(3 * k) * 0.01
        nu = rng.multivariate_normal(np.zeros(3 * k), S)
        bad = rng.choice(k, size=int(rng.integers(1, k)), replace=False)
        for b in bad:  # outliers
            nu[3 * b : 3 * b + 3] += rng.normal(size=3) * 2.0
        z = nu.reshape(k, 3)
        det, cand = np.arange(k), np.arange(k)
        out_det, _, n_drop = _joint_compatible(det, cand, None, z, np.zeros((k, 3)), None, None, cfg,
                                               lambda d, c, S=S: S[np.ix_(np.concatenate([np.arange(3 * i, 3 * i + 3) for i in c]),
                                                                          np.concatenate([np.arange(3 * i, 3 * i + 3) for i in c]))])
        kept, dropped = _brute_force_drop_order(nu, S, lambda n: chi2.ppf(cfg.joint_confidence, 3 * n))
        assert sorted(out_det.tolist()) == kept, trial
        assert n_drop == len(dropped)


def test_too_few_pairs_cannot_re_place_an_uncertain_prediction():
    """One or two pairs whose prediction is far less certain than the measurement (an uncertain
    rover: a clutter point in an old landmark's wide gate) are dropped; three, or one well
    predicted pair, are kept."""
    cfg = AssociationConfig()
    R = np.tile(np.eye(3) * 0.02**2, (3, 1, 1))
    zhat = np.array([[3.0, 0.0, 0.0], [5.0, 2.0, 0.0], [6.0, -3.0, 0.0]])
    z = zhat + 0.01
    wide = np.tile(np.eye(3) * 0.2**2, (3, 1, 1))  # 10 sigma of the detection
    lone = associate(z[:1], R[:1], zhat, wide, cfg)
    assert (lone.landmark_of == -1).all() and lone.n_uncertain_dropped == 1
    two = associate(z[:2], R[:2], zhat, wide, cfg)
    assert (two.landmark_of == -1).all() and two.n_uncertain_dropped == 2
    three = associate(z, R, zhat, wide, cfg)
    np.testing.assert_array_equal(three.landmark_of, [0, 1, 2])
    assert three.n_uncertain_dropped == 0
    sure = associate(z[:1], R[:1], zhat, np.tile(np.eye(3) * 0.02**2, (3, 1, 1)), cfg)
    assert sure.landmark_of[0] == 0
    off = associate(z[:1], R[:1], zhat, wide, AssociationConfig(min_pairs_uncertain=1))
    assert off.landmark_of[0] == 0


def _shared_pose_cov(S_pose, Rz, old):
    """Joint innovation covariance of pairs whose landmarks in ``old`` share the pose error
    ``S_pose`` (landmarks mapped before a blind spell) while the others moved with the pose
    (mapped since: predicted as well as measured)."""

    def joint_cov(det, cand):
        k = len(det)
        S = np.zeros((3 * k, 3 * k))
        for a in range(k):
            for b in range(k):
                if cand[a] in old and cand[b] in old:
                    S[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] += S_pose
            S[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] += Rz[det[a]]
        return S

    return joint_cov


def test_an_uncertain_pair_with_a_compatible_alternative_is_not_associated():
    """After a blind spell (1 m of pose sigma) one detection falls near two old landmarks 0.8 m
    apart; two well predicted pairs on rocks mapped since the spell say nothing about which:
    the pair is dropped (the wrong one re-placed the rover with centimetre confidence), the well
    predicted ones kept, and the detection is neither associated nor new."""
    S_pose = np.eye(3) * 1.0**2
    Rz = np.tile(np.eye(3) * 0.02**2, (3, 1, 1))
    zhat = np.array([[3.0, 1.0, 0.0], [3.0, 1.8, 0.0], [5.0, -2.0, 0.0], [6.0, 2.0, 0.0]])
    old = {0, 1}
    S_hat = np.stack([S_pose, S_pose, Rz[0], Rz[0]])
    z = np.array([[3.3, 1.5, 0.0], [5.01, -2.0, 0.0], [6.0, 2.01, 0.0]])  # the rover 0.3 / 0.5 m off
    joint_cov = _shared_pose_cov(S_pose, Rz, old)
    a = associate(z, Rz, zhat, S_hat, joint_cov=joint_cov)
    assert a.n_ambiguous_dropped == 1
    assert a.landmark_of.tolist() == [-1, 2, 3]
    assert not a.is_new.any() and a.n_ambiguous == 1
    off = associate(z, Rz, zhat, S_hat, AssociationConfig(ambiguity_test=False), joint_cov=joint_cov)
    assert off.landmark_of[0] in (0, 1) and off.n_ambiguous_dropped == 0
    # the other way round: two detections in one old landmark's gate
    z2 = np.array([[3.3, 1.5, 0.0], [3.3, 0.7, 0.0], [5.01, -2.0, 0.0], [6.0, 2.01, 0.0]])
    Rz2 = np.tile(np.eye(3) * 0.02**2, (4, 1, 1))
    a2 = associate(z2, Rz2, zhat[[0, 2, 3]], S_hat[[0, 2, 3]], joint_cov=_shared_pose_cov(S_pose, Rz2, {0}))
    assert a2.n_ambiguous_dropped == 1 and a2.landmark_of.tolist() == [-1, -1, 1, 2]


def test_uncertain_pairs_that_the_others_tie_down_are_kept():
    """Three old landmarks seen again after a blind spell, with a fourth 1 m from one of them:
    each gate (1 m of pose sigma) holds a rival, but the shared pose error the other pairs fix
    makes the swap jointly incompatible, so the rover is re-placed."""
    S_pose = np.eye(3) * 1.0**2
    zhat = np.array([[3.0, -2.0, 0.0], [4.0, 2.0, 0.0], [7.0, 0.0, 0.0], [7.0, 1.0, 0.0]])
    S_hat = np.tile(S_pose, (4, 1, 1))
    z = zhat[:3] + np.array([0.5, 0.3, 0.0])
    Rz = np.tile(np.eye(3) * 0.02**2, (3, 1, 1))
    joint_cov = _shared_pose_cov(S_pose, Rz, {0, 1, 2, 3})
    a = associate(z, Rz, zhat, S_hat, joint_cov=joint_cov)
    assert a.landmark_of.tolist() == [0, 1, 2]
    assert a.n_ambiguous_dropped == 0 and a.n_uncertain_dropped == 0


def test_a_joint_covariance_that_is_not_positive_definite_passes_nothing():
    """A caller's joint covariance with a direction of negative variance (an inconsistent model)
    gave joint distances below zero, and any set of pairs passed; the direction now reads as
    near-certain and the pairs that disagree along it are dropped."""
    zhat = np.array([[3.0, -1.0, 0.0], [4.0, 1.0, 0.0], [5.0, 0.0, 0.0]])
    z = zhat.copy()
    z[0] += [0.6, 0.0, 0.0]  # 0.6 m off, inside its own (1 m) gate, and the others are not
    Rz = np.tile(np.eye(3) * 0.02**2, (3, 1, 1))
    S_hat = np.tile(np.eye(3) * 1.0, (3, 1, 1))

    def indefinite(det, cand):
        k = len(det)
        S = np.kron(np.ones((k, k)), np.eye(3) * 1.0)
        for i in range(k):
            S[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += Rz[det[i]]
        v = np.zeros(3 * k)
        v[0] = 1.0  # pair 0's x: variance pushed below zero
        return S - 3.0 * np.outer(v, v)

    a = associate(z, Rz, zhat, S_hat, AssociationConfig(min_pairs_uncertain=1, ambiguity_test=False),
                  joint_cov=indefinite)
    assert a.landmark_of[0] == -1 and a.n_jc_dropped >= 1

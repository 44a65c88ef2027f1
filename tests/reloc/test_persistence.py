"""Temporal persistence of associations (reloc.persistence): a rock's detections agree from frame
to frame within their covariances; clutter that falls inside a landmark's gate does not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from reloc.association import AssociationConfig
from reloc.persistence import RecentDetections, RecentFrames, place_agrees

GATE = AssociationConfig().gate_chi2
R = np.diag([0.03, 0.02, 0.02]) ** 2  # a rock 6-8 m away: stereo covariance, world frame


def _confirm(rd, lid, t, x, cov=R, window=1.6, slack=0.0):
    return bool(rd.confirm(np.array([lid]), t, np.reshape(x, (1, 3)), cov[None], window, GATE, slack)[0])


def test_a_detection_is_confirmed_only_by_an_earlier_one_at_the_same_place_within_the_window():
    rd = RecentDetections()
    x = np.array([5.0, 1.0, 0.2])
    assert not _confirm(rd, 7, 10.0, x)  # first sighting: nothing before it
    assert _confirm(rd, 7, 10.5, x + [0.02, -0.01, 0.0])  # the next frame, same place
    assert not _confirm(rd, 7, 11.0, x + [0.5, 0.0, 0.0])  # 0.5 m off: another point
    assert not _confirm(rd, 8, 11.0, x)  # another landmark's record does not count
    assert not _confirm(rd, 7, 20.0, x)  # everything before is older than the window
    assert not _confirm(rd, 9, 30.0, x) and not _confirm(rd, 9, 30.0, x)  # the same frame is not "before"
    # the slack widens the gate by the relative pose change between two frames
    assert not _confirm(rd, 11, 40.0, x) and not _confirm(rd, 11, 40.5, x + [0.15, 0.0, 0.0])
    assert _confirm(rd, 12, 50.0, x) is False and _confirm(rd, 12, 50.5, x + [0.15, 0.0, 0.0], slack=0.05**2)


def test_window_zero_passes_everything_and_remembers_nothing():
    rd = RecentDetections()
    ok = rd.confirm(np.arange(3), 1.0, np.zeros((3, 3)), np.tile(R, (3, 1, 1)), 0.0, GATE)
    assert ok.all() and len(rd) == 0


def test_record_seeds_a_new_landmark_and_copies_sweeps_and_forget_are_independent():
    rd = RecentDetections(depth=2)
    x = np.array([3.0, 0.0, 0.0])
    rd.record(np.array([1]), 0.0, x[None], R[None])
    snap = rd.copy()
    assert _confirm(rd, 1, 0.5, x)
    rd.forget([1])
    assert not _confirm(rd, 1, 1.0, x + [1.0, 0, 0])  # forgotten: nothing to confirm against
    assert _confirm(snap, 1, 0.5, x)  # the snapshot kept its own record
    # a sweep forgets landmarks with nothing within the longest window used
    rd2 = RecentDetections()
    _confirm(rd2, 5, 0.0, x)
    _confirm(rd2, 6, 100.0, x)
    assert len(rd2) == 1
    with pytest.raises(ValueError, match="depth must be >= 1"):
        RecentDetections(depth=0)


def test_a_rocks_detections_pass_at_the_gate_level_and_clutter_in_its_gate_seldom_does():
    """Sampled: two detections of one rock with their covariances pass as often as the chi2 gate
    says (99 %); clutter spread uniformly over an association gate 5x the measurement sigma (a
    landmark predicted with some pose uncertainty) passes in a few per cent of the pairs."""
    rng = np.random.default_rng(0)
    n = 4000
    L = np.linalg.cholesky(R)
    rock = np.array([6.0, 2.0, 0.1])
    true_ok = clutter_ok = 0
    S = 25.0 * R + R  # the association gate's covariance
    Ls = np.linalg.cholesky(S)
    for k in range(n):
        rd = RecentDetections()
        a = rock + L @ rng.standard_normal(3)
        b = rock + L @ rng.standard_normal(3)
        _confirm(rd, 0, 0.0, a)
        true_ok += _confirm(rd, 0, 0.5, b)
        # two clutter points uniform inside the gate ellipsoid of the same landmark
        u = rng.standard_normal((2, 3))
        u *= (rng.uniform(size=(2, 1)) ** (1 / 3)) * np.sqrt(GATE) / np.linalg.norm(u, axis=1, keepdims=True)
        c = rock + u @ Ls.T
        _confirm(rd, 1, 0.0, c[0])
        clutter_ok += _confirm(rd, 1, 0.5, c[1])
    p = true_ok / n
    assert abs(p - chi2.cdf(GATE, 3)) < 0.01, p
    assert clutter_ok / n < 0.05, clutter_ok / n


def test_a_landmark_starts_only_from_a_second_sighting_at_the_same_place():
    from reloc.persistence import PendingDetections

    pd = PendingDetections()
    cov = np.tile(R, (2, 1, 1))
    a, b = np.array([4.0, 1.0, 0.0]), np.array([8.0, -2.0, 0.1])
    assert not pd.confirm(0.0, np.stack([a, b]), cov, 1.6, GATE).any()  # first sightings wait
    assert len(pd) == 2
    # the next frame: a again (within noise), b's place empty, a clutter point elsewhere
    ok = pd.confirm(0.5, np.stack([a + [0.01, 0.0, 0.0], [6.0, 3.0, 0.0]]), cov, 1.6, GATE)
    assert ok.tolist() == [True, False]
    assert len(pd) == 2  # a's first sighting used up; b waits; the clutter point is a first sighting
    # one first sighting confirms one detection only (the nearer of two)
    ok = pd.confirm(1.0, np.stack([b + [0.03, 0, 0], b + [0.005, 0, 0]]), cov, 1.6, GATE)
    assert ok.tolist() == [False, True]
    # first sightings older than the window are gone; window 0 lets everything through
    assert not pd.confirm(5.0, b[None], R[None], 1.6, GATE).any()
    assert pd.confirm(6.0, np.zeros((3, 3)), np.tile(R, (3, 1, 1)), 0.0, GATE).all()
    snap = pd.copy()
    assert pd.confirm(5.5, b[None], R[None], 1.6, GATE).all()
    assert snap.confirm(5.5, b[None], R[None], 1.6, GATE).all()  # the copy kept its own


def test_the_slack_grows_with_range_for_a_heading_the_odometry_does_not_follow():
    from reloc.persistence import slack_variance

    v = slack_variance(0.02, 0.005, np.array([0.0, 10.0]))
    assert np.allclose(v, [0.02**2, 0.02**2 + 0.05**2])
    # a point 10 m ahead (stereo: 10 cm in range, 1 cm sideways), the heading 12 mrad off between
    # the two frames (2.5 s of a 0.005 rad/s drift the odometry does not see): 12 cm sideways
    far = np.diag([0.1, 0.01, 0.01]) ** 2
    rd = RecentDetections()
    x = np.array([10.0, 0.0, 0.0])
    moved = x + [0.0, 0.12, 0.0]
    assert not _confirm(rd, 1, 0.0, x, far)
    assert not _confirm(rd, 1, 0.5, moved, far, slack=slack_variance(0.02, 0.0, [10.0]))
    rd = RecentDetections()
    assert not _confirm(rd, 1, 0.0, x, far)
    assert _confirm(rd, 1, 0.5, moved, far, slack=slack_variance(0.02, 0.005, [10.0]))


def test_an_uncertain_pair_needs_two_earlier_detections_at_the_same_place():
    """A landmark predicted far less certainly than it is measured (a rock unseen through a blind
    spell) needs two earlier detections that agree: a rock detected frame after frame passes one
    frame later, clutter that agreed once by chance does not."""
    from reloc.persistence import persistence_agree

    ac = AssociationConfig(persistence_n_uncertain=2)
    S_sure, S_wide = np.tile(R, (1, 1, 1)), np.tile(np.eye(3) * 0.2**2, (1, 1, 1))
    assert persistence_agree(ac, S_sure, R[None]).tolist() == [1]
    assert persistence_agree(ac, S_wide, R[None]).tolist() == [2]  # trace ratio 70 > 16
    assert persistence_agree(AssociationConfig(), S_wide, R[None]).tolist() == [1]  # the default: one
    x = np.array([2.0, 0.5, 0.0])
    rd = RecentDetections()

    def confirm(t, p, need):
        return bool(rd.confirm(np.array([4]), t, p[None], R[None], 2.5, GATE, 0.0, need)[0])

    assert not confirm(10.0, x, 2)
    assert not confirm(11.0, x + 0.01, 2)  # one earlier detection agrees: not enough
    assert confirm(12.0, x - 0.01, 2)  # two agree
    rd2 = RecentDetections()
    assert not rd2.confirm(np.array([4]), 10.0, x[None], R[None], 2.5, GATE, 0.0, 2)[0]
    rd2.confirm(np.array([4]), 11.0, (x + [0.6, 0, 0])[None], R[None], 2.5, GATE, 0.0, 2)  # elsewhere in the gate
    assert not rd2.confirm(np.array([4]), 12.0, (x + 0.01)[None], R[None], 2.5, GATE, 0.0, 2)[0]  # one of two


def test_recent_frames_count_earlier_frames_with_a_detection_at_the_place_whatever_became_of_it():
    """RecentFrames (AssociationConfig.persistence_any_detection): per detection, the distinct
    earlier frames of the window that held a detection at its world position, associated or not."""
    rf = RecentFrames()
    x = np.array([5.0, 1.0, 0.2])
    far = np.array([9.0, -3.0, 0.1])
    count = lambda t, pts, window=2.5, slack=0.0: rf.count(t, np.reshape(pts, (-1, 3)),
                                                         np.tile(R, (len(np.reshape(pts, (-1, 3))), 1, 1)),
                                                         window, GATE, slack)
    assert count(10.0, x).tolist() == [0] and len(rf) == 0  # nothing recorded yet
    rf.record(10.0, np.array([x, x + [0.01, 0, 0]]), np.tile(R, (2, 1, 1)), 2.5)  # two points, one frame
    rf.record(11.0, np.array([x + [0.02, -0.01, 0], far]), np.tile(R, (2, 1, 1)), 2.5)
    assert count(12.0, [x, far, x + [0.5, 0, 0]]).tolist() == [2, 1, 0]  # frames, not detections
    assert count(11.0, x).tolist() == [1]  # the frame of t itself is not "before"
    assert count(12.0, x, window=1.5).tolist() == [1]  # the frame at 10 s is out of a 1.5 s window
    assert count(12.0, x + [0.25, 0, 0]).tolist() == [0]
    assert count(12.0, x + [0.25, 0, 0], slack=0.1**2).tolist() == [2]  # the pose change between frames
    rf.record(20.0, far[None], R[None], 2.5)  # recording forgets frames older than the window
    assert len(rf) == 1 and count(20.5, x).tolist() == [0] and count(20.5, far).tolist() == [1]
    snap = rf.copy()
    rf.record(21.0, x[None], R[None], 2.5)
    assert len(snap) == 1 and len(rf) == 2
    assert count(22.0, np.zeros((0, 3))).shape == (0,)


def test_place_agrees_retries_only_uncertain_pairs_of_landmarks_not_detected_lately():
    """place_agrees: a refused pair passes by place only where it needed more than one agreeing
    detection, its landmark had no detection in the window, and as many earlier frames held a
    detection at its position; passed pairs stay passed; the input is not changed."""
    x = np.array([5.0, 1.0, 0.2])
    frames = RecentFrames()
    for t in (10.0, 11.0):  # two frames with something at x
        frames.record(t, x[None], R[None], 2.5)
    recent = RecentDetections()
    recent.record(np.array([7]), 10.5, x[None] + 3.0, R[None])  # landmark 7 detected lately (elsewhere)
    ok = np.array([False, False, False, False, True])
    need = np.array([2, 1, 2, 3, 2])
    ids = np.array([1, 2, 7, 3, 4])
    xyz, cov = np.tile(x, (5, 1)), np.tile(R, (5, 1, 1))
    got = place_agrees(ok, need, ids, 12.0, xyz, cov, recent, frames, 2.5, GATE, np.zeros(5))
    # 1: uncertain, not seen lately, two frames at its place -> passes; 2: needed one (certain) and
    # was refused by its own record -> stays refused; 7: seen lately -> its record rules; 3: needs
    # three frames, two held one -> refused; 4: passed already
    assert got.tolist() == [True, False, False, False, True]
    assert ok.tolist() == [False, False, False, False, True]
    far = place_agrees(ok, need, ids, 12.0, xyz + 1.0, cov, recent, frames, 2.5, GATE, np.zeros(5))
    assert far.tolist() == ok.tolist()  # nothing at that place


def test_clutter_seldom_agrees_with_two_earlier_frames_by_place():
    """Sampled: clutter spread over a 3 x 3 m gate, three points a frame, agrees by place with two
    earlier frames (what an uncertain pair needs) in far fewer draws than a rock does (always
    within its covariance: at the gate's 99 %, squared)."""
    rng = np.random.default_rng(3)
    rock, n, clutter_ok, rock_ok = np.array([6.0, 0.0, 0.0]), 400, 0, 0
    for _ in range(n):
        rf = RecentFrames()
        for t in (0.0, 1.0):
            pts = np.vstack([rock + rng.multivariate_normal(np.zeros(3), R),
                             rock + rng.uniform(-1.5, 1.5, (3, 3)) * [1, 1, 0.1]])
            rf.record(t, pts, np.tile(R, (4, 1, 1)), 2.5)
        rock_ok += int(rf.count(2.0, (rock + rng.multivariate_normal(np.zeros(3), R))[None], R[None], 2.5, GATE)[0] >= 2)
        clutter = rock + rng.uniform(-1.5, 1.5, 3) * [1, 1, 0.1]
        clutter_ok += int(rf.count(2.0, clutter[None], R[None], 2.5, GATE)[0] >= 2)
    assert rock_ok / n > 0.95
    assert clutter_ok / n < 0.02

"""The bound on the EKF state (``EkfConfig.max_landmarks``) where more landmarks are in view than
it holds: a landmark still seen is not swapped for a new one (``keep_seen_s``), and a kind's
reserved share (craters: ``kinds.craters.reserved_landmarks``) is not taken by another kind that
comes more often and in greater numbers (on rocky-1km the rocks left the craters no slot)."""

from __future__ import annotations

import numpy as np
import pytest

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.craters import CraterObservations
from reloc.errors import ConfigError
from reloc.kinds import kind_code
from reloc.measurements import RockObservations

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))
SIGMA = 0.02  # m, per axis


def _rocks(n: int) -> np.ndarray:
    """``n`` rock centres in base_link ahead of the rover, 1.5 m apart (unambiguous)."""
    k = np.arange(n)
    return np.stack([3.0 + 1.5 * (k // 8), -5.25 + 1.5 * (k % 8), np.zeros(n)], axis=1)


def _rock_frame(t: float, xyz: np.ndarray) -> RockObservations:
    n = len(xyz)
    return RockObservations(t, xyz, np.tile(np.eye(3) * SIGMA**2, (n, 1, 1)), np.full(n, 0.5), np.full(n, 0.9))


def _crater_frame(t: float) -> CraterObservations:
    xyz = np.array([[18.0, -6.0, 0.0], [20.0, 4.0, 0.0], [16.0, 9.0, 0.0]])
    return CraterObservations(t, xyz, np.tile(np.eye(3) * 0.1**2, (3, 1, 1)), [6.0, 8.0, 5.0], [0.3, 0.4, 0.25],
                              [0.9, 0.9, 0.9], [0.9, 0.9, 0.9])


def _drive_rocks(cfg: EkfConfig, seconds: float = 20.0) -> tuple[EkfSlam, list[set[int]]]:
    """30 rocks in view, each detected in a frame with probability 0.8 (seeded), 4 frames a
    second: more than the 25 the state holds. Returns the filter and its landmark ids after
    each frame."""
    rng = np.random.default_rng(3)
    ekf = EkfSlam(START, cfg)
    xyz = _rocks(30)
    ids = []
    for t in np.arange(0.25, seconds, 0.25):
        ekf.observe(_rock_frame(t, xyz[rng.random(30) < 0.8]))
        ids.append(set(ekf._s.book.ids.tolist()))
    return ekf, ids


def test_a_landmark_still_in_view_is_not_swapped_for_a_new_one():
    ekf, ids = _drive_rocks(EkfConfig(max_landmarks=25, keep_seen_s=2.0))  # a long traverse's setting
    # the first frame's rocks are first sightings (reloc.persistence): a rock is mapped from its
    # second sighting, so the map holds the 25 from the third frame on, and keeps them throughout
    assert ids[0] == set() and ids[1] < ids[-1]
    assert len(ids[-1]) == 25 and all(x == ids[-1] for x in ids[2:])
    assert ekf.stats().extra["n_initialised"] == 25 and ekf.stats().extra["n_evicted"] == 0
    churn, churn_ids = _drive_rocks(EkfConfig(max_landmarks=25))
    # by age alone (the default): whatever a frame missed is swapped for what it saw
    assert churn.stats().extra["n_initialised"] > 5 * 25
    assert len(churn_ids[2]) == 25 and len(churn_ids[-1] & churn_ids[2]) < 25


def _rocks_and_craters(reserved: int) -> EkfSlam:
    """Rock frames fill the 25-landmark state (every rock seen in every frame), then crater
    frames come once a second among the rock frames."""
    ekf = EkfSlam(START, EkfConfig(max_landmarks=25, kinds={"craters": {"reserved_landmarks": reserved}}))
    rocks = _rocks(30)
    for t in np.arange(0.25, 30.0, 0.25):
        ekf.observe(_rock_frame(t, rocks))
        if t >= 10.0 and abs(t % 1.0) < 1e-9:
            ekf.observe(_crater_frame(t + 0.01))
    return ekf


def test_craters_keep_their_reserved_share_beside_a_state_full_of_rocks():
    ekf = _rocks_and_craters(reserved=4)
    book = ekf._s.book
    craters = book.kind == kind_code("craters")
    assert craters.sum() == 3 and book.confirmed[craters].all()
    assert len(ekf.landmark_map("craters")) == 3
    # the craters took their slots from the rocks, and the rocks do not take the fourth back
    assert (book.kind == kind_code("rocks")).sum() == 25 - 3
    # the crater landmarks stayed from their first frame on: one initialisation each
    assert ekf.stats().extra["crater_n_initialised"] == 3
    starved = _rocks_and_craters(reserved=0)
    assert (starved._s.book.kind == kind_code("craters")).sum() == 0  # what the reserve prevents


def test_a_reserve_larger_than_the_bound_is_refused_naming_the_key():
    ekf = EkfSlam(START, EkfConfig(max_landmarks=10, kinds={"craters": {"reserved_landmarks": 11}}))
    with pytest.raises(ConfigError, match="reserved_landmarks"):
        ekf.observe(_crater_frame(1.0))

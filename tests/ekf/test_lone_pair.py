"""A frame whose only association stands beside an ambiguous detection is not used: a lone pair
has no joint-compatibility check, and an ambiguous scene is where a wrong pair hides."""

from __future__ import annotations

import dataclasses

import numpy as np

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.association import AssociationConfig
from reloc.backend import PoseEstimate
from reloc.measurements import RockObservations
from reloc.odometry import OdometryStep

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-2, 1e-2, 1e-4, 1e-6, 1e-6, 1e-4]))


def frame(t: float, xyz: list[list[float]], sigma_m: float = 0.01) -> RockObservations:
    n = len(xyz)
    return RockObservations(t=t, xyz_base_m=np.array(xyz, float), cov_base_m2=np.tile(np.eye(3) * sigma_m**2, (n, 1, 1)),
                            size_m=np.full(n, 0.3), score=np.full(n, 0.9))


def run(skip: bool) -> tuple[EkfSlam, np.ndarray, np.ndarray]:
    # persistence off: the rocks are mapped from one frame (this checks the lone-pair rule alone)
    ekf = EkfSlam(START, dataclasses.replace(EkfConfig(), skip_lone_ambiguous_pair=skip,
                                             association=AssociationConfig(persistence_s=0.0)))
    rocks = [[3.0, 0.0, 0.0], [4.0, 2.0, 0.0], [5.0, -2.0, 0.0]]
    ekf.observe(frame(0.5, rocks))
    for k in range(10):  # drive 1 m forward: the pose becomes uncertain on its own
        t0 = 0.5 + 0.25 * k
        ekf.predict(OdometryStep(t0, t0 + 0.25, 0.4, 0.0, np.eye(3), np.eye(3), np.zeros(3)))
    before = ekf.estimate()
    # two detections next to the first rock (now 2 m ahead): one is assigned, the other gates to
    # the same rock and is neither assigned nor new (ambiguous); the other rocks are not seen
    ekf.observe(frame(3.0, [[2.06, 0.0, 0.0], [1.97, 0.01, 0.0]]))
    return ekf, before.position_m, ekf.estimate().position_m


def test_lone_pair_beside_an_ambiguous_detection_is_not_used():
    ekf, p0, p1 = run(skip=True)
    assert np.array_equal(p0, p1)
    assert ekf.stats().extra["n_lone_pairs_skipped"] == 1
    ekf_off, q0, q1 = run(skip=False)
    assert ekf_off.stats().extra["n_lone_pairs_skipped"] == 0
    assert np.linalg.norm(q1 - q0) > 1e-3  # without the rule the lone pair moves the rover

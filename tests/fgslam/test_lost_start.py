"""Lost and found: from a start 15 m and 30 deg off (its covariance saying 50 m), the relocalizer
searches the whole catalog, the back-end re-anchors on the first fix, and the prior-guided path
takes over (seeded synthetic traverse, the constellation matcher)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _synth_stream import make_stream

from fgslam.backends.reanchor import Reanchoring, is_lost, planar_motion
from fgslam.backends.registry import make_backend
from fgslam.fix_sources import OnlineFixes
from fgslam.relocalizer import Relocalizer
from fgslam.runner import ground_truth_trajectory, run_backend
from reloc.backend import PoseEstimate
from reloc.measurements import GroundTruthPose


def test_planar_motion_takes_one_pose_onto_another():
    D = planar_motion(np.array([1.0, 2.0, 0.3]), np.array([-4.0, 5.0, 1.2]))
    p = D @ np.array([1.0, 2.0, 0.0, 1.0])
    assert np.allclose(p[:2], [-4.0, 5.0]) and np.isclose(np.arctan2(D[1, 0], D[0, 0]), 0.9)


@pytest.fixture(scope="module")
def lost_inputs():
    inputs = make_stream(seed=3, duration_s=50.0)
    T = inputs.initial.T_world_base.copy()
    D = planar_motion(np.zeros(3), np.array([15.0, -6.0, np.radians(30.0)]))
    cov = np.diag([50.0**2, 50.0**2, 0.01**2, 1e-4, 1e-4, np.radians(30.0) ** 2])
    return inputs, dataclasses.replace(inputs, initial=PoseEstimate(inputs.initial.t, D @ T, cov))


@pytest.mark.parametrize("backend", ["ekf", "isam2"])
def test_a_lost_start_recovers_on_its_first_fix(lost_inputs, backend):
    inputs, lost = lost_inputs
    assert is_lost(lost.initial) and not is_lost(inputs.initial)
    be = make_backend(backend, lost.initial)
    assert isinstance(be, Reanchoring)
    reloc = Relocalizer(lost.catalog)
    res = run_backend(be, lost.measurements, OnlineFixes([reloc]))
    assert len(be.reanchors) == 1 and not be.lost
    first = next(a for a in res.attempts if a.fix is not None)
    assert first.t_meas < 20.0  # time to first fix
    gt = ground_truth_trajectory([m for m in inputs.measurements if isinstance(m, GroundTruthPose)])
    est = res.final
    after = est.t > be.reanchors[0]["t"] + 2.0
    idx = np.searchsorted(gt.t, est.t[after]).clip(0, len(gt) - 1)
    err = np.linalg.norm(est.T_world_base[after, :2, 3] - gt.T_world_base[idx, :2, 3], axis=1)
    assert err.max() < 0.5, err.max()
    # after the re-anchoring the fixes take the prior-guided path and reach the back-end as usual
    later = [o for o in res.outcomes[1:] if o.accepted]
    assert len(later) >= 3 and res.outcomes[0].reason.startswith("re-anchored")

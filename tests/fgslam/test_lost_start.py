"""Lost and found: from a start 15 m and 30 deg off (its covariance saying 50 m), the relocalizer
searches the whole catalog, the back-end re-anchors on the first fix, and the prior-guided path
takes over (seeded synthetic traverse, the constellation matcher)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _synth_stream import make_stream

from fgslam.backends.reanchor import Reanchoring, anchor_cov, is_lost, planar_motion, split_start
from fgslam.backends.registry import make_backend
from fgslam.fix_sources import OnlineFixes
from fgslam.relocalizer import Relocalizer
from fgslam.runner import ground_truth_trajectory, run_backend
from reloc.backend import PoseEstimate
from reloc.measurements import GlobalFix, GroundTruthPose


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
    # the attempts by status: what the whole-catalog search made of them, counted per relocalizer
    from fgslam.compare import attempts_by_status

    counts = attempts_by_status(res.attempts)
    assert sum(sum(c.values()) for c in counts.values()) == len(res.attempts)
    assert sum(c.get("fix", 0) for c in counts.values()) == sum(a.fix is not None for a in res.attempts)


@pytest.mark.parametrize("backend", ["ekf", "isam2"])
def test_a_lost_start_standing_still_keeps_every_update(backend):
    """A rover that stands still at a lost start (50 m, 0.52 rad, as --start-sigma gives it):
    iSAM2 with the wide prior in its graph had its first keyframe refused as an indeterminate
    system (a 50 m sigma beside millimetres of odometry); the anchor keeps it out, and the
    reported covariance still says lost by the start's sigma."""
    from fgslam.compare import run_metrics
    from fgslam.inputs import StartSpec

    inputs = make_stream(seed=3, duration_s=6.0, speed_mps=0.0)
    start = StartSpec(sigma_xy_m=50.0, sigma_yaw_rad=0.52)
    be = make_backend(backend, PoseEstimate(inputs.initial.t, inputs.initial.T_world_base, start.cov()))
    res = run_backend(be, inputs.measurements)
    health = run_metrics(res, None, res.attempts, 1.0).get("solver_health", {})
    assert health.get("n_failed_updates", 0) == 0 and health.get("n_recoveries", 0) == 0
    assert ("factorization" in health) == (backend == "isam2")
    est = be.estimate()
    assert be.lost and est.planar_sigma_m == pytest.approx(50.0, rel=1e-3)
    assert np.sqrt(est.cov[5, 5]) == pytest.approx(0.52, rel=1e-2)
    traj = be.trajectory()
    assert np.all(np.sqrt(traj.cov[:, 0, 0]) > 49.9)


def test_the_anchor_covariance_is_the_start_uncertainty_carried_to_each_pose():
    """A start shifted by (dx, dy, dz) and turned by dyaw about p0 moves a pose at p by
    dp + dyaw z x (p - p0) and turns it by dyaw: the sampled spread of poses so moved matches
    ``anchor_cov`` (first order, small perturbations)."""
    rng = np.random.default_rng(7)
    p0 = np.array([3.0, -2.0, 1.0])
    p = np.array([[40.0, 25.0, 4.0], [3.0, -2.0, 1.0], [-60.0, 10.0, -3.0]])
    S = np.diag([0.2, 0.1, 0.05, 1e-3]) ** 2
    S[0, 3] = S[3, 0] = 0.5 * 0.2 * 1e-3
    d = rng.multivariate_normal(np.zeros(4), S, 20000)
    for pk, C in zip(p, anchor_cov(S, p0, p)):
        c, s = np.cos(d[:, 3]), np.sin(d[:, 3])
        r = pk[:2] - p0[:2]
        moved = np.column_stack([p0[0] + c * r[0] - s * r[1] + d[:, 0], p0[1] + s * r[0] + c * r[1] + d[:, 1],
                                 pk[2] + d[:, 2]])
        e = np.column_stack([moved - pk, d[:, 3]])
        emp = np.cov(e.T)
        sel = [0, 1, 2, 5]
        scale = np.sqrt(np.outer(np.diag(emp), np.diag(emp)))  # sampling error ~ scale / sqrt(n)
        assert np.all(np.abs(C[np.ix_(sel, sel)] - emp) <= 0.04 * scale)
        assert np.allclose(C[3:5, :], 0.0) and np.allclose(C[:, 3:5], 0.0)


def test_a_lost_start_splits_into_a_known_start_and_its_anchor_and_a_known_one_is_not_wrapped():
    inputs = make_stream(seed=3, duration_s=2.0)
    lost = PoseEstimate(inputs.initial.t, inputs.initial.T_world_base,
                        np.diag([30.0**2, 30.0**2, 1.0, 1e-4, 1e-4, 0.3**2]))
    inner, anchor = split_start(lost)
    assert inner.planar_sigma_m < 0.1 and np.allclose(inner.cov[3:5, 3:5], 1e-4 * np.eye(2))
    assert np.allclose(np.diag(anchor), [30.0**2 - 1e-4, 30.0**2 - 1e-4, 1.0 - 1e-4, 0.3**2 - 0.002**2])
    be = make_backend("ekf", inputs.initial)
    assert not isinstance(be, Reanchoring)


@pytest.mark.parametrize("backend", ["ekf", "isam2"])
def test_a_reanchoring_far_from_the_start_adds_only_the_odometry_since_t_meas(backend):
    """Re-anchored at a fix measured 2 s before it arrives, the back-end's new covariance is the
    fix's plus the odometry's growth over those 2 s, taken from the wrapped back-end's own
    estimates: not the start's yaw uncertainty swinging a pose tens of metres out (the anchor's
    lever arm, ~(0.52 rad x 10 m)^2 of variance), which the fix replaces."""
    inputs = make_stream(seed=3, duration_s=60.0)
    cov = np.diag([50.0**2, 50.0**2, 0.01**2, 1e-4, 1e-4, 0.52**2])
    be = make_backend(backend, PoseEstimate(inputs.initial.t, inputs.initial.T_world_base, cov))
    run_backend(be, [m for m in inputs.measurements if m.t <= 45.0])
    traj = be.inner.trajectory()
    k = int(np.searchsorted(traj.t, traj.t[-1] - 2.0))
    t_meas, then_cov = float(traj.t[k]), traj.cov[k]
    now_inner, now = be.inner.estimate(), be.estimate()
    assert np.linalg.norm(now.position_m[:2] - inputs.initial.T_world_base[:2, 3]) > 8.0
    assert be.lost and np.sqrt(now.cov[0, 0] + now.cov[1, 1]) > 50.0
    pose = traj.T_world_base[k]
    yaw = float(np.arctan2(pose[1, 0], pose[0, 0]))
    fix_cov = np.diag([0.3**2, 0.3**2, 0.02**2])
    out = be.apply_fix(GlobalFix(t_meas, now.t, pose[0, 3] + 1.0, pose[1, 3] - 2.0, yaw + 0.1, fix_cov))
    assert out.accepted and out.reason.startswith("re-anchored") and not be.lost
    growth = np.diag(now_inner.cov) - np.diag(then_cov)
    assert np.all(growth[[0, 1, 5]] >= -1e-12) and np.all(growth[[0, 1]] < 0.01)
    got = be.inner.estimate().cov
    assert got[0, 0] + got[1, 1] == pytest.approx(fix_cov[0, 0] + fix_cov[1, 1] + growth[0] + growth[1], rel=0.05)
    assert got[5, 5] == pytest.approx(fix_cov[2, 2] + growth[5], rel=0.05)


class _MapOnly:
    """A back-end stand-in that holds a pose and one mapped crater (relative to its start)."""

    name, config = "stub", None

    def __init__(self, initial: PoseEstimate) -> None:
        self.initial = initial

    def estimate(self) -> PoseEstimate:
        return self.initial

    def landmark_map(self, kind: str):
        from reloc.backend import LandmarkMap

        xy = self.initial.position_m[:2] + np.array([10.0, 2.0])
        return LandmarkMap(np.array([4]), np.array([[*xy, 0.0]]), (0.1**2 * np.eye(3))[None], np.array([3.0]),
                           np.array([6]), kind)


def test_a_lost_starts_map_holds_the_anchor_so_no_tight_gate_identifies_a_chance_crater():
    """While lost, a landmark is placed only relative to the start, so its world covariance holds
    the start's uncertainty as the estimate's does (the map's convention): the map reported
    carries the anchor. Without it a crater's gate would be 0.1 m wide where the rover is 50 m
    unsure, and a chance catalog crater in it would be identified with a small false-alarm bound
    and re-anchor the rover on it."""
    from fgslam.crater_relocalizer import CraterRelocalizer
    from reloc.measurements import RockCatalog

    T = np.eye(4)
    T[:2, 3] = [200.0, 100.0]
    lost = PoseEstimate(0.0, T, np.diag([50.0**2, 50.0**2, 0.01**2, 1e-4, 1e-4, np.radians(30.0) ** 2]))
    be = Reanchoring(_MapOnly, lost)
    inner = be.inner.landmark_map("craters")
    lmap = be.landmark_map("craters")
    _, anchor = split_start(lost)
    extra = anchor_cov(anchor, lost.position_m, inner.xyz_world_m)[:, :3, :3]
    assert np.allclose(lmap.cov_world_m2, inner.cov_world_m2 + extra)
    assert np.sqrt(lmap.cov_world_m2[0, 0, 0]) > 49.0 and np.allclose(lmap.xyz_world_m, inner.xyz_world_m)
    # a chance crater of the same size 0.1 m from where the lost rover put its crater, the rest
    # of the young catalog hundreds of metres away
    rng = np.random.default_rng(4)
    far = rng.uniform(-2000.0, 2000.0, (60, 2))
    far = far[np.linalg.norm(far - inner.xyz_world_m[0, :2], axis=1) > 300.0]
    cat = RockCatalog(np.vstack([inner.xyz_world_m[0, :2] + [0.1, 0.0], far]),
                      np.concatenate([[3.0], rng.uniform(1.0, 6.0, len(far))]), np.ones(len(far) + 1))
    cfg = {"min_new_observations": 0, "min_travel_m": 0.0, "min_turn_deg": 0.0}
    est = be.estimate()
    assert CraterRelocalizer(cat, cfg).attempt({"craters": inner}, est).status == "fix"  # the tight gate's wrong fix
    assert CraterRelocalizer(cat, cfg).attempt({"craters": lmap}, est).status == "too few landmarks"

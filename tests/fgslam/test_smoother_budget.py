"""Per-frame observation budget of the smoother (reloc.budget): on a dense synthetic yard a rock
frame adds at most ``max_observations`` factors of graph landmarks and inserts at most
``max_new`` landmarks where ``dense_view`` graph landmarks are in view; what is left out is
counted; the estimate stays inside its 3-sigma
bounds and close to the unbudgeted one."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.config import LandmarkConfig
from fgslam.smoother.landmarks import FrameAssociation, LandmarkStore
from fgslam.smoother.synthetic import SyntheticConfig, ate_m, drive, simulate_synthetic
from reloc.budget import ObservationBudget


def _spy(store: LandmarkStore, log: list) -> None:
    """Record the FrameAssociation of every frame."""
    inner = store.associate_frame

    def wrapped(*a, **kw) -> FrameAssociation:
        fa = inner(*a, **kw)
        log.append(fa)
        return fa

    store.associate_frame = wrapped


def _run(budget: ObservationBudget):
    run = simulate_synthetic(SyntheticConfig(seed=3, duration_s=60.0, rock_density_per_m2=0.6))
    sm = Isam2Smoother(run.initial_pose, SmootherConfig(landmarks=LandmarkConfig(budget=budget, dense_view=0)))
    frames: list[FrameAssociation] = []
    _spy(sm.kinds.get("rocks").store, frames)
    out = drive(sm, run.measurements)
    return run, sm, frames, out


@pytest.fixture(scope="module")
def runs():
    return _run(ObservationBudget(max_observations=12, max_new=4)), _run(ObservationBudget())


def test_dense_frame_adds_at_most_the_budget(runs):
    (_, sm, frames, _), (_, sm_all, frames_all, _) = runs
    assert max(len(fa.observed) for fa in frames_all) > 20  # dense enough to bind
    assert max(len(fa.observed) for fa in frames) <= 12
    assert max(len(fa.to_insert) for fa in frames) <= 4
    extra = sm.stats().extra
    assert extra["n_budget_skipped"] > 0 and extra["n_budget_new_skipped"] > 0
    assert sm_all.stats().extra["n_budget_skipped"] == 0
    assert sm.kinds.get("rocks").store.n_budget_skipped == extra["n_budget_skipped"]


def test_budgeted_estimate_stays_within_its_bounds(runs):
    (run, sm, _, out), (run_all, sm_all, _, _) = runs
    inside = []
    for t, T, C in zip(out.est_t, out.est_T, out.est_cov):
        e = run.gt_at(t)[:3, 3] - T[:3, 3]
        inside.append(np.all(np.abs(e[:2]) <= 3.0 * np.sqrt(np.diag(C)[:2])))
    assert np.mean(inside) > 0.9
    tr, tr_all = sm.trajectory(), sm_all.trajectory()
    ate, ate_all = ate_m(run, tr.t, tr.T_world_base), ate_m(run_all, tr_all.t, tr_all.T_world_base)
    assert ate <= 2.0 * ate_all + 0.02, (ate, ate_all)


def test_new_landmarks_are_bounded_only_where_the_view_is_dense():
    def room(dense_view: int, max_new: int, n_in_view: int):
        cfg = LandmarkConfig(budget=ObservationBudget(25, max_new), dense_view=dense_view)
        return LandmarkStore(cfg)._insert_room(n_in_view)

    assert room(60, 3, 60) == 3 and room(60, 3, 75) == 3  # a dense view: at most max_new
    assert room(60, 3, 12) == np.inf  # a sparse yard is not held back
    assert room(0, 3, 12) == 3  # 0: bounded everywhere
    assert room(60, 0, 100) == np.inf  # max_new 0: no bound

"""Per-frame observation budget of the EKF (reloc.budget): on a dense synthetic yard a frame uses
at most ``max_observations`` associated rocks and initialises at most ``max_new``; what is left out
is counted; the estimate stays inside its 3-sigma bounds and close to the unbudgeted one."""

from __future__ import annotations

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate
from reloc.budget import ObservationBudget, select_observations
from reloc.errors import ConfigError

START = PoseEstimate(0.0, np.eye(4), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))


def run_filter(budget: ObservationBudget, seed: int = 5):
    """30 s on a dense yard (~60 rocks per frame); returns the filter, per-frame reports and
    the (error, 3-sigma) of the position once per second."""
    run = simulate(seed, duration_s=30.0, frame_every=15, n_rocks=1200)
    ekf = EkfSlam(START, EkfConfig(budget=budget))
    reports, samples = [], []
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            reports.append(ekf.observe(run.frames[k]))
        if k % 30 == 29:
            e = ekf.estimate()
            samples.append((run.truth_p[k + 1] - e.position_m, 3.0 * np.sqrt(np.diag(e.cov[:3, :3]))))
    return ekf, reports, samples


@pytest.fixture(scope="module")
def runs():
    return run_filter(ObservationBudget(max_observations=10, max_new=6)), run_filter(ObservationBudget())


def test_dense_frame_uses_at_most_the_budget(runs):
    (ekf, reports, _), (ekf_all, reports_all, _) = runs
    assert max(r.n_associated for r in reports_all) > 20  # the yard is dense enough to bind
    assert max(r.n_associated for r in reports) <= 10
    assert max(r.n_new for r in reports) <= 6
    extra = ekf.stats().extra
    assert extra["n_budget_skipped"] > 0 and extra["n_budget_new_skipped"] > 0
    # every association is either used or counted as skipped
    assert extra["n_associated"] == sum(r.n_associated for r in reports) + extra["n_budget_skipped"]
    assert extra["n_initialised"] == sum(r.n_new for r in reports)
    assert ekf_all.stats().extra["n_budget_skipped"] == 0


def test_budgeted_estimate_stays_within_its_bounds(runs):
    (_, _, samples), (_, _, samples_all) = runs
    err = np.array([e for e, _ in samples])
    bound = np.array([b for _, b in samples])
    assert np.mean(np.all(np.abs(err) <= bound, axis=1)) >= 0.95
    err_all = np.linalg.norm([e for e, _ in samples_all], axis=1)
    assert np.sqrt(np.mean(np.linalg.norm(err, axis=1) ** 2)) <= 2.0 * np.sqrt(np.mean(err_all**2)) + 0.02


def test_selection_prefers_map_landmarks_then_low_cost():
    in_map = np.array([False, True, True, False, True])
    cost = np.array([0.1, 0.5, 0.2, 0.05, 0.9])
    assert select_observations(in_map, cost, 2).tolist() == [1, 2]
    assert select_observations(in_map, cost, 4).tolist() == [1, 2, 3, 4]
    assert select_observations(in_map, cost, 0).tolist() == [0, 1, 2, 3, 4]  # 0: no bound
    assert select_observations(in_map, cost, 9).tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ConfigError):
        ObservationBudget(max_observations=-1)

"""Two-sided NEES tests: chi-square bounds by hand, effective sample sizes, verdicts both ways."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from fgslam import nees as N


def test_interval_is_the_chi_square_quantiles_of_the_summed_nees():
    # 50 runs of a 3-dof error: 50 * ANEES ~ chi2(150); the 95 % bounds by hand from the quantiles
    lo, hi = N.nees_interval(3, 50)
    assert lo == pytest.approx(chi2.ppf(0.025, 150) / 50) and hi == pytest.approx(chi2.ppf(0.975, 150) / 50)
    assert lo == pytest.approx(2.36, abs=0.005) and hi == pytest.approx(3.72, abs=0.005)
    lo1, hi1 = N.nees_interval(2, 1)  # a single 2-dof sample: chi2_2 quantiles
    assert lo1 == pytest.approx(-2 * np.log(0.975)) and hi1 == pytest.approx(-2 * np.log(0.025))
    with pytest.raises(N.NeesError):
        N.nees_interval(0, 10)


def test_independent_samples_consistent_and_both_failures_detected(rng):
    x = rng.chisquare(2, 2000)
    ok = N.nees_test(x, 2, correlated=False)
    assert ok.verdict is N.Verdict.CONSISTENT and ok.n_eff == 2000
    assert N.nees_test(4.0 * x, 2, correlated=False).verdict is N.Verdict.OPTIMISTIC  # covariance 4x too small
    assert N.nees_test(0.25 * x, 2, correlated=False).verdict is N.Verdict.PESSIMISTIC  # 4x too large


def test_correlated_series_gets_a_small_effective_size(rng):
    """An AR(1) error with rho = 0.98: NEES of e^2 has tau = (1 + rho^2) / (1 - rho^2) ~ 50."""
    from scipy.signal import lfilter

    n, rho = 200_000, 0.98
    e = lfilter([1.0], [1.0, -rho], rng.standard_normal((n, 2)) * np.sqrt(1 - rho**2), axis=0)
    nees = np.sum(e**2, axis=1)
    tau = N.integrated_autocorrelation_time(nees)
    assert 40 < tau < 60
    t = N.nees_test(nees, 2)
    assert t.n == n and t.n_eff == pytest.approx(n / tau)
    # the raw-sample interval would be far too narrow for this mean; the effective one holds it
    assert t.verdict is N.Verdict.CONSISTENT
    assert t.interval[1] - t.interval[0] > 5 * np.diff(N.nees_interval(2, n))[0]


def test_whitened_ar1_error_keeps_the_textbook_tau(rng):
    """Estimated from the whitened errors about zero, the NEES's tau of an AR(1) error is
    (1 + a^2) / (1 - a^2) (Isserlis: the NEES's autocorrelation is the error's squared)."""
    from scipy.signal import lfilter

    n, a = 200_000, 0.98
    w = lfilter([1.0], [1.0, -a], rng.standard_normal((n, 2)) * np.sqrt(1 - a**2), axis=0)
    tau = N.nees_autocorrelation_time(w)
    assert tau == pytest.approx((1 + a**2) / (1 - a**2), rel=0.15)
    t = N.whitened_test(w)
    assert t.dof == 2 and t.n == n and t.n_eff == pytest.approx(n / tau)
    assert t.mean == pytest.approx(np.mean(np.sum(w**2, axis=1))) and t.verdict is N.Verdict.CONSISTENT
    white = N.whitened_test(rng.standard_normal((4000, 3)))
    assert white.n_eff > 3500 and white.verdict is N.Verdict.CONSISTENT


def test_a_persistent_offset_is_one_draw_not_many(rng):
    """A rover stuck for 600 samples with one constant error inside its covariance: the NEES's
    fluctuations about its own mean look nearly independent (a large n_eff and a narrow interval
    that calls 3.3 optimistic); about zero the window holds one draw of the error."""
    w = np.array([1.2, -1.35]) + 0.05 * rng.standard_normal((600, 2))  # NEES ~ 3.3, 2 dof
    nees = np.sum(w**2, axis=1)
    naive = N.nees_test(nees, 2)
    assert naive.n_eff > 50 and naive.verdict is N.Verdict.OPTIMISTIC
    t = N.whitened_test(w)
    assert t.n_eff < 2.0 and t.verdict is N.Verdict.CONSISTENT
    # a covariance 100x too small over the same window is still caught: one draw of NEES 330
    assert N.whitened_test(10.0 * w).verdict is N.Verdict.OPTIMISTIC


def test_whiten_is_the_cholesky_whitening_and_flags_bad_covariances(rng):
    A = rng.standard_normal((50, 3, 3))
    P = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    e = rng.standard_normal((50, 3))
    w = N.whiten(e, P)
    np.testing.assert_allclose(np.sum(w**2, axis=1), np.einsum("ki,ki->k", e, np.linalg.solve(P, e[:, :, None])[:, :, 0]))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", np.linalg.cholesky(P), w), e, atol=1e-12)
    bad = P.copy()
    bad[3] = -np.eye(3)
    bad[7, 0, 0] = np.nan
    wb = N.whiten(e, bad)
    assert np.isnan(wb[[3, 7]]).all() and np.isfinite(np.delete(wb, [3, 7], axis=0)).all()
    np.testing.assert_allclose(N.whiten(e[:, 0], P[:, 0, 0])[:, 0], e[:, 0] / np.sqrt(P[:, 0, 0]))
    t = N.whitened_test(wb)
    assert t.n == 48


def test_pooled_runs_are_tested_with_the_sum_of_effective_sizes(rng):
    runs = [N.nees_test(rng.chisquare(1, 500), 1, correlated=False) for _ in range(4)]
    p = N.pooled_test(runs)
    assert p.n == 2000 and p.n_eff == pytest.approx(2000)
    assert p.mean == pytest.approx(np.mean([r.mean for r in runs]))
    assert p.interval == pytest.approx(N.nees_interval(1, 2000))
    assert N.NeesTest.from_dict(p.to_dict()) == p
    empty = N.nees_test(np.array([np.nan]), 1)
    assert empty.verdict is N.Verdict.UNTESTED and N.pooled_test([empty]).verdict is N.Verdict.UNTESTED
    with pytest.raises(N.NeesError, match="one dimension"):
        N.pooled_test([runs[0], N.nees_test(rng.chisquare(2, 10), 2, correlated=False)])


def test_campaign_anees_pools_the_seeds_records():
    """The campaign summary's ANEES: records' (mean, n, n_eff) pooled as by hand."""
    from fgslam.campaign.aggregate import aggregate, summary_markdown

    def rec(seed, mean, n, n_eff):
        run = {"nees_position": {"mean": mean, "n": n, "n_eff": n_eff, "dof": 2},
               "nees_yaw": {"mean": None, "n": 0, "n_eff": None, "dof": 1}}
        return {"key": f"w/v/{seed}", "world": "w", "variant": "v", "seed": seed, "status": "ok",
                "result": {"runs": {"ekf": run}}, "runtime": {}}

    records = [rec(0, 1.5, 100, 10.0), rec(1, 2.5, 300, 30.0)]
    summary = aggregate(records)
    pos = summary["groups"][0]["anees"]["ekf"]["position"]
    assert pos["mean"] == pytest.approx((1.5 * 100 + 2.5 * 300) / 400) and pos["n_eff"] == pytest.approx(40.0)
    assert pos["interval"] == pytest.approx(list(N.nees_interval(2, 40.0)))
    assert pos["seeds"] == 2 and "yaw" not in summary["groups"][0]["anees"]["ekf"]
    assert "ANEES across seeds" in summary_markdown(summary, records)

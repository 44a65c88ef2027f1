"""Block copy used to marginalise landmarks, and the in-place symmetric rank-2m covariance update."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ekf.state import take_symmetric


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 2**31 - 1), runs=st.integers(1, 20))
def test_take_symmetric_equals_fancy_indexing(n, seed, runs):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, n))
    cols = np.flatnonzero(rng.random(n) < 0.7)
    if cols.size == 0:
        cols = np.array([0])
    np.testing.assert_array_equal(take_symmetric(P, cols, max_runs=runs), P[np.ix_(cols, cols)])


@settings(max_examples=25, deadline=None)
@given(n=st.sampled_from([5, 130, 520, 600]), m=st.integers(1, 12), seed=st.integers(0, 2**31 - 1))
def test_sym_rank2_update_matches_the_dense_formula(n, m, seed):
    from ekf.updates import sym_rank2_update

    rng = np.random.default_rng(seed)
    A0 = rng.normal(size=(n, n))
    P0 = A0 @ A0.T
    K, X = rng.normal(size=(n, m)), rng.normal(size=(n, m))
    P = P0.copy()
    out = sym_rank2_update(P, K, X)
    assert out is P
    np.testing.assert_allclose(out, P0 + K @ X.T + X @ K.T, rtol=0, atol=1e-9 * np.abs(P0).max())
    assert np.array_equal(out, out.T)


def test_the_joint_innovation_covariance_equals_the_dense_product():
    """The association's joint covariance of k rock pairs, built on 3-row slices, is the dense
    ``H P H^T`` over the head and the pairs' landmark columns (in any order of the columns)."""
    from ekf.rocks import joint_innovation_cov, stacked_jacobian

    rng = np.random.default_rng(3)
    for h, k, n in ((9, 1, 30), (12, 5, 60), (15, 40, 200)):
        A = rng.normal(size=(n, n))
        P = A @ A.T
        rows = rng.choice((n - h) // 3, size=k, replace=False)  # landmarks in no particular order
        cols = (h + 3 * rows[:, None] + np.arange(3)).reshape(-1)
        H_head, H_l = rng.normal(size=(k, 3, h)), rng.normal(size=(3, 3))
        idx = np.concatenate([np.arange(h), cols])
        Hc = stacked_jacobian(H_head, H_l)
        np.testing.assert_allclose(joint_innovation_cov(P, h, cols, H_head, H_l), Hc @ P[np.ix_(idx, idx)] @ Hc.T,
                                   rtol=1e-10, atol=1e-9)

"""Marginal covariances of many variables in one top-down pass over a Gaussian Bayes tree.

A clique holds the conditional ``R x_F + S x_S = d`` (unit noise after whitening) of its frontal
variables F given its separator S, so with the separator's marginal ``P_SS`` (a block of the
parent clique's joint marginal, which covers S):

    P_FS = -R^-1 S P_SS,    P_FF = R^-1 R^-T - P_FS (R^-1 S)^T.

Going from the roots down gives every clique's joint marginal from its parent's: exact, one
dense triangular inverse per clique, and cliques without children whose frontal variables are
not asked for (most landmark leaves) are skipped. ``gtsam.Marginals`` computes each key's
marginal separately through Bayes-tree shortcuts: on my2020 (303 keyframes, 1349 landmarks)
4.3 s CPU for all keyframes against 0.13 s here (one BLAS thread), equal to 1e-10 relative.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from scipy.linalg import solve_triangular


class CovarianceRecoveryError(RuntimeError):
    """The Bayes tree holds a conditional this pass cannot invert (a constrained noise model)."""


def _whitened(cond: gtsam.GaussianConditional) -> tuple[np.ndarray, np.ndarray]:
    R, S = np.asarray(cond.R(), dtype=float), np.asarray(cond.S(), dtype=float)
    model = cond.get_model()
    if model is not None:
        sigmas = np.asarray(model.sigmas(), dtype=float)
        if not np.all(sigmas > 0):
            raise CovarianceRecoveryError("constrained conditional in the Bayes tree")
        if not np.allclose(sigmas, 1.0):
            R, S = R / sigmas[:, None], S / sigmas[:, None]
    return R, S


def tree_marginals(bayes_tree: gtsam.GaussianBayesTree, dim_of: Callable[[int], int],
                   wanted: set[int]) -> dict[int, np.ndarray]:
    """Marginal covariance (d, d) of every key in ``wanted`` found in ``bayes_tree``; ``dim_of(key)``
    gives a variable's tangent dimension."""
    out: dict[int, np.ndarray] = {}
    stack = [(c, None, None) for c in bayes_tree.roots()]
    while stack:
        clique, parent_offsets, parent_cov = stack.pop()
        cond = clique.conditional()
        keys = list(cond.keys())
        n_children = clique.nrChildren()
        dims = [dim_of(k) for k in keys]
        n_frontal_dim = int(np.asarray(cond.R()).shape[0])
        n_frontal = int(np.searchsorted(np.cumsum(dims), n_frontal_dim)) + 1
        want = [k for k in keys[:n_frontal] if k in wanted]
        if not n_children and not want:
            continue
        R, S = _whitened(cond)
        Rinv = solve_triangular(R, np.eye(n_frontal_dim), lower=False, check_finite=False)
        sep = keys[n_frontal:]
        if sep:
            idx = np.concatenate([parent_offsets[k] for k in sep])
            P_ss = parent_cov[np.ix_(idx, idx)]
            A = Rinv @ S
            P_fs = -A @ P_ss
            P_ff = Rinv @ Rinv.T - P_fs @ A.T
        else:
            P_ff = Rinv @ Rinv.T
        starts = np.concatenate([[0], np.cumsum(dims)])
        offsets = {k: np.arange(starts[i], starts[i + 1]) for i, k in enumerate(keys)}
        for k in want:
            o = offsets[k]
            out[k] = P_ff[o[0]:o[-1] + 1, o[0]:o[-1] + 1].copy()
        if n_children:
            joint = np.block([[P_ff, P_fs], [P_fs.T, P_ss]]) if sep else P_ff
            stack.extend((clique[j], offsets, joint) for j in range(n_children))
    return out

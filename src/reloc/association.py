"""Data association of stereo rock detections with landmarks, shared by both back-ends.

1. Mahalanobis gating of every (detection i, landmark j) pair with ``S_ij = S_hat_j + R_z_i``.
2. A globally consistent one-to-one assignment (Hungarian, ``linear_sum_assignment``) on the gated
   squared distances, so two nearby rocks never both take the same landmark.
3. Joint compatibility: the stacked innovation of the assigned pairs is tested against
   ``chi2(3k)``; while it fails, the pair whose removal lowers the joint distance most is dropped. With a
   ``joint_cov`` callback the test uses the full innovation covariance (pose error shared by every
   pair, as in JCBB); without it, the block-diagonal one.
4. Ambiguity of the uncertain pairs (predicted far less certainly than measured, as after a blind
   spell): a pair whose detection or landmark has another partner inside its gate, with which
   the jointly compatible set stays jointly compatible, is not associated; one frame cannot tell
   the two hypotheses apart, and the wrong one re-places the rover with centimetre confidence.
5. A detection farther than ``new_landmark_chi2`` from every landmark is a new landmark; one
   between the two thresholds, or one that lost its landmark to a better detection, is ambiguous
   and rejected. Two new detections compatible with each other keep only the closer one.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.linalg.lapack import dpotri as potri
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from reloc.config import Ge, Interval, NonNegative, Positive, checked
from reloc.errors import MeasurementError

_NO_MATCH = 1e12
_REINVERT_EVERY = 8  # joint compatibility: fresh inverse after this many downdates (round-off)


@functools.lru_cache(maxsize=4096)
def _chi2_limit(confidence: float, dof: int) -> float:
    """chi2 quantile (scipy's ppf costs ~0.5 ms; a frame asks for a handful of dof values)."""
    return float(chi2.ppf(confidence, dof))


@dataclass(frozen=True)
@checked()
class AssociationConfig:
    """Gates of :func:`associate` (squared Mahalanobis distances, 3 dof)."""

    gate_chi2: Positive = 11.345  # 99 % for 3 dof: a pair inside may be associated
    new_landmark_chi2: Positive = 16.27  # 99.9 %: beyond this from every landmark -> new landmark
    max_range_m: Positive = 12.0  # detections farther than this are ignored (stereo too noisy)
    joint_confidence: Annotated[float, Interval(gt=0, lt=1)] = 0.99  # joint-compatibility test level for chi2(3k)
    max_size_ratio: Annotated[float, Ge(1)] = 3.0  # a pair whose size estimates differ by more than this is not gated
    # fewer jointly compatible pairs than this, each predicted far less certainly than it is
    # measured (trace(S_hat) > uncertain_ratio x trace(R)), are not associated: one or two pairs
    # cannot re-place an uncertain rover (after a blind spell any clutter point falls into the
    # wide gates of the old landmarks, and a lone pair has no joint test to fail)
    min_pairs_uncertain: Annotated[int, Ge(1)] = 3
    uncertain_ratio: Positive = 16.0  # 4 sigma: 4.0 (2 sigma) dropped sparse cnes pairs in normal running (EKF ATE 0.056 -> 0.078 m)
    # temporal persistence (reloc.persistence, applied by the back-ends after associate): a pair is
    # used only when its landmark had a detection at the same world position (within gate_chi2 on
    # the two detections' covariances plus, per axis, persistence_slack_m and persistence_slack_rad
    # times the range: pose change between the frames that the odometry may not model) in the
    # persistence_s seconds before; clutter inside a gate seldom has one. 0: off. Set to span two
    # or three of the back-end's frames (the EKF takes rock frames at 2 Hz; the smoother at 1 Hz)
    persistence_s: NonNegative = 1.6
    persistence_slack_m: NonNegative = 0.02
    persistence_slack_rad: NonNegative = 0.0  # 0.005 let clutter through on no_rocks (iSAM2 0.013 -> 0.268 m at the end)
    # earlier detections that must agree when the pair is uncertain (trace(S_hat) > uncertain_ratio
    # x trace(R), as above): after a blind spell the old landmarks' gates are wide and clutter
    # inside one agrees with the clutter of the frame before often enough to re-place the rover
    # (iSAM2, my2020 seed 1, clutter only for 2 min: three lone clutter pairs on rocks unseen for
    # 95-126 s, 2 m away, took it from 0.16 to 0.44 m off at a 0.10 m sigma); a rock detected
    # again frame after frame passes one frame later
    persistence_n_uncertain: Annotated[int, Ge(1)] = 1
    # an uncertain pair whose landmark has no detection at all in the window passes when as many
    # earlier frames held a detection at its world position all the same, associated or not
    # (reloc.persistence.RecentFrames): back on a sparse field after a long blind stretch, frames
    # of one or two detections are refused whole (min_pairs_uncertain) and the landmarks are
    # associated only every few frames, never twice in the window (iSAM2, ERC MY2021 seed 0, 120 m:
    # the rover back at its start area 2.7 m off, 77 detections refused in 50 s, never re-placed)
    persistence_any_detection: bool = False
    # an uncertain pair (as above) is dropped when swapping its landmark for another one inside the
    # detection's gate, or its detection for another one inside the landmark's gate, leaves the
    # pairs jointly compatible: the frame cannot tell which is right (EKF, my2021 seed 0, 2 min
    # camera blackout: 1.1 m of position sigma, one detection with 4 old rocks in its gate, the
    # nearest one wrong; two well predicted pairs on rocks mapped since the spell moved with the
    # pose and passed the joint test: 2.16 m off at a 3 cm sigma)
    ambiguity_test: bool = True


@dataclass(frozen=True)
class Association:
    """Result of :func:`associate` for N detections against M candidate landmarks.

    ``landmark_of`` (N,) int: candidate index or -1; ``is_new`` (N,) bool: initialise a landmark;
    ``d2`` (N,): squared Mahalanobis distance of the chosen pair (inf if none);
    ``n_ambiguous``: detections rejected as ambiguous; ``n_out_of_range``: beyond ``max_range_m``;
    ``n_jc_dropped``: pairs dropped by the joint-compatibility test; ``n_uncertain_dropped``: pairs
    dropped as too few for an uncertain prediction (``AssociationConfig.min_pairs_uncertain``);
    ``n_ambiguous_dropped``: uncertain pairs with a jointly compatible alternative
    (``AssociationConfig.ambiguity_test``).
    """

    landmark_of: np.ndarray
    is_new: np.ndarray
    d2: np.ndarray
    n_ambiguous: int
    n_out_of_range: int = 0
    n_jc_dropped: int = 0
    n_uncertain_dropped: int = 0
    n_ambiguous_dropped: int = 0

    @property
    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(detection indices, candidate indices) of the associated pairs, (k,) each."""
        det = np.flatnonzero(self.landmark_of >= 0)
        return det, self.landmark_of[det]


def uncertain_pairs(config: AssociationConfig, S_hat: np.ndarray, R_z: np.ndarray) -> np.ndarray:
    """(k,) bool: pairs whose landmark is predicted far less certainly than it is measured,
    ``trace(S_hat) > config.uncertain_ratio * trace(R_z)`` (``S_hat``, ``R_z`` (k, 3, 3))."""
    tr_S = np.trace(np.reshape(S_hat, (-1, 3, 3)), axis1=1, axis2=2)
    tr_R = np.trace(np.reshape(R_z, (-1, 3, 3)), axis1=1, axis2=2)
    return tr_S > config.uncertain_ratio * tr_R


def pairwise_d2(
    z_base: np.ndarray, R_z: np.ndarray, zhat_base: np.ndarray, S_hat: np.ndarray, cap: float = np.inf
) -> np.ndarray:
    """Squared Mahalanobis distances (N, M) of detections (N, 3) to predictions (M, 3), ``S = S_hat_j + R_z_i``.

    Pairs whose cheap lower bound ``|nu|^2 / trace(S)`` already exceeds ``cap`` get that bound
    instead of the exact value (enough to compare against gates up to ``cap``)."""
    nu = z_base[:, None, :] - zhat_base[None, :, :]
    tr = np.trace(S_hat, axis1=1, axis2=2)[None, :] + np.trace(R_z, axis1=1, axis2=2)[:, None]
    d2 = np.einsum("nmi,nmi->nm", nu, nu) / tr
    near = d2 <= cap
    if near.any():
        i, j = np.nonzero(near)
        S = S_hat[j] + R_z[i]
        v = nu[i, j]
        d2[i, j] = np.einsum("ki,ki->k", v, np.linalg.solve(S, v[..., None])[..., 0])
    return d2


def _check(name: str, arr: np.ndarray, shape: tuple) -> np.ndarray:
    arr = np.asarray(arr, dtype=float)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise MeasurementError(f"associate: {name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MeasurementError(f"associate: {name} contains NaN or inf")
    return arr


def associate(
    z_base: np.ndarray,
    R_z: np.ndarray,
    zhat_base: np.ndarray,
    S_hat: np.ndarray,
    config: AssociationConfig = AssociationConfig(),
    size_z: np.ndarray | None = None,
    size_hat: np.ndarray | None = None,
    joint_cov: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> Association:
    """Associate detections ``z_base`` (N, 3) m, covariance ``R_z`` (N, 3, 3), with predicted
    landmark measurements ``zhat_base`` (M, 3) in base_link and their covariance ``S_hat``
    (M, 3, 3) (``H P H^T`` without R). Optional sizes (N,), (M,) in metres veto pairs whose
    diameters disagree. ``joint_cov(det_idx, cand_idx)`` -> (3k, 3k) full innovation covariance
    (R included) of k pairs, in that order, for the joint-compatibility test."""
    z_base = _check("z_base", np.reshape(z_base, (-1, 3)), (None, 3))
    n = z_base.shape[0]
    R_z = _check("R_z", np.reshape(R_z, (-1, 3, 3)), (n, 3, 3))
    zhat_base = _check("zhat_base", np.reshape(zhat_base, (-1, 3)), (None, 3))
    m = zhat_base.shape[0]
    S_hat = _check("S_hat", np.reshape(S_hat, (-1, 3, 3)), (m, 3, 3))

    landmark_of = np.full(n, -1, dtype=int)
    d2_out = np.full(n, np.inf)
    in_range = np.linalg.norm(z_base, axis=1) <= config.max_range_m
    n_out = int(n - in_range.sum())
    d2 = pairwise_d2(z_base, R_z, zhat_base, S_hat, config.new_landmark_chi2) if m else np.full((n, 0), np.inf)
    d2[~in_range] = np.inf
    d2_min = d2.min(axis=1) if m else np.full(n, np.inf)

    gated = d2 < config.gate_chi2
    if size_z is not None and size_hat is not None and m:
        sz = _check("size_z", np.reshape(size_z, (-1,)), (n,))
        sh = _check("size_hat", np.reshape(size_hat, (-1,)), (m,))
        ratio = np.maximum(sz[:, None], 1e-6) / np.maximum(sh[None, :], 1e-6)
        gated &= (ratio <= config.max_size_ratio) & (ratio >= 1.0 / config.max_size_ratio)

    rows_ok = np.flatnonzero(gated.any(axis=1))
    cols_ok = np.flatnonzero(gated.any(axis=0))
    if rows_ok.size:
        cost = np.where(gated[np.ix_(rows_ok, cols_ok)], d2[np.ix_(rows_ok, cols_ok)], _NO_MATCH)
        r, c = linear_sum_assignment(cost)
        keep = cost[r, c] < _NO_MATCH
        det, cand = rows_ok[r[keep]], cols_ok[c[keep]]
        det, cand, n_jc = _joint_compatible(det, cand, d2, z_base, zhat_base, R_z, S_hat, config, joint_cov)
        n_amb = 0
        if config.ambiguity_test and det.size:
            det, cand, n_amb = _unambiguous(det, cand, gated, z_base, zhat_base, R_z, S_hat, config, joint_cov)
        n_unc = 0
        if 0 < det.size < config.min_pairs_uncertain:
            if np.all(uncertain_pairs(config, S_hat[cand], R_z[det])):
                det, cand, n_unc = det[:0], cand[:0], int(det.size)
        landmark_of[det] = cand
        d2_out[det] = d2[det, cand]
    else:
        n_jc = n_unc = n_amb = 0

    is_new = in_range & (d2_min > config.new_landmark_chi2) & (landmark_of < 0)
    is_new = _dedupe_new(is_new, z_base, R_z, config.gate_chi2)
    n_ambiguous = int(np.sum(in_range & (landmark_of < 0) & ~is_new))
    return Association(landmark_of, is_new, d2_out, n_ambiguous, n_out, n_jc, n_unc, n_amb)


def _joint_matrix(det, cand, R_z, S_hat, joint_cov) -> np.ndarray:
    """(3k, 3k) symmetric innovation covariance of pairs (det, cand): the caller's full one, or the
    block-diagonal ``S_hat + R_z`` without a callback."""
    if joint_cov is not None:
        S = np.asarray(joint_cov(det, cand), dtype=float)
    else:
        S = np.zeros((3 * det.size, 3 * det.size))
        for i in range(det.size):
            S[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = S_hat[cand[i]] + R_z[det[i]]
    return 0.5 * (S + S.T)


def _joint_d2(det, cand, z_base, zhat_base, R_z, S_hat, joint_cov) -> float:
    """Joint squared Mahalanobis distance of the stacked innovation of pairs (det, cand)."""
    nu = (z_base[det] - zhat_base[cand]).reshape(-1)
    S = _joint_matrix(det, cand, R_z, S_hat, joint_cov)
    try:
        return float(nu @ cho_solve(cho_factor(S, lower=True, check_finite=False), nu, check_finite=False))
    except LinAlgError:
        return float(nu @ _pd_inverse(S) @ nu)


def _pd_inverse(S: np.ndarray) -> np.ndarray:
    """Inverse of a joint covariance that Cholesky refused (round-off, or a caller's covariance
    that is not positive definite): its eigenvalues floored at 1e-9 of the largest, so that a
    direction of negative variance reads as a near-certain one (the test fails there) instead of
    giving a joint distance below zero (the test passes whatever the pairs)."""
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    w = np.maximum(w, 1e-9 * max(float(w.max()), 1e-300))
    return (V / w) @ V.T


def _replaced(a: np.ndarray, k: int, value: int) -> np.ndarray:
    out = a.copy()
    out[k] = value
    return out


def _unambiguous(det, cand, gated, z_base, zhat_base, R_z, S_hat, config, joint_cov):
    """Drop the uncertain pairs of a jointly compatible set (det, cand) that have a jointly
    compatible alternative: another landmark in the detection's gate, or another detection in the
    landmark's gate, not taken by a kept pair; returns (det, cand, n_dropped). Pairs predicted
    about as well as they are measured are not tested (their gates seldom hold two rocks, and two
    neighbours in a tight gate are told apart by the assignment)."""
    unc = uncertain_pairs(config, S_hat[cand], R_z[det])
    if not unc.any():
        return det, cand, 0
    limit = _chi2_limit(config.joint_confidence, 3 * det.size)
    ambiguous = np.zeros(det.size, dtype=bool)
    for k in np.flatnonzero(unc):
        swaps = [(det, _replaced(cand, k, j)) for j in np.flatnonzero(gated[det[k]]) if j not in cand]
        swaps += [(_replaced(det, k, i), cand) for i in np.flatnonzero(gated[:, cand[k]]) if i not in det]
        ambiguous[k] = any(_joint_d2(d, c, z_base, zhat_base, R_z, S_hat, joint_cov) <= limit for d, c in swaps)
    return det[~ambiguous], cand[~ambiguous], int(ambiguous.sum())


def _joint_compatible(det, cand, d2, z_base, zhat_base, R_z, S_hat, config, joint_cov):
    """While the stacked innovation fails chi2(3k), drop the pair whose removal lowers the joint
    distance most; returns (det, cand, n_dropped).

    One inverse, then a downdate per dropped pair: with ``Y = S^-1`` and ``y = Y nu``, removing
    pair i (block b) leaves the joint distance ``nu^T S^-1 nu - y_b^T Y_bb^-1 y_b`` (the Schur
    complement), so all k candidates cost k 3x3 solves instead of k solves of size 3k; the
    covariance of the kept pairs is the sub-matrix of the current one, so the callback is asked
    once. The inverse stays full size: a dropped block is downdated out in place (a rank-3
    update) and zeroed, which costs one pass over the matrix and no copy (a 100-pair frame of a
    kilometre traverse dropped 20-40 pairs)."""
    n_dropped = 0
    if not det.size:
        return det, cand, 0
    nu = (z_base[det] - zhat_base[cand]).reshape(-1)
    S = _joint_matrix(det, cand, R_z, S_hat, joint_cov)
    try:  # most frames pass as they are: one Cholesky solve, no inverse
        c = cho_factor(S, lower=True, check_finite=False)
        if float(nu @ cho_solve(c, nu, check_finite=False)) <= _chi2_limit(config.joint_confidence, 3 * det.size):
            return det, cand, 0
        Y = _cho_inverse(c[0])
    except LinAlgError:  # not positive definite: the floored inverse below
        Y = None
    kept = np.ones(det.size, dtype=bool)
    while True:
        k = int(kept.sum())
        if Y is None or (n_dropped and n_dropped % _REINVERT_EVERY == 0):
            Y = _kept_inverse(S, kept)
        y = Y @ nu
        if float(nu @ y) <= _chi2_limit(config.joint_confidence, 3 * k):
            break
        if k == 1:
            return det[:0], cand[:0], n_dropped + 1
        idx = np.flatnonzero(kept)
        Yb = Y.reshape(det.size, 3, det.size, 3)[idx, :, idx, :]  # (k, 3, 3) diagonal blocks
        yb = y.reshape(-1, 3)[idx]
        reduction = np.einsum("ki,ki->k", yb, np.linalg.solve(Yb, yb[..., None])[..., 0])
        best = int(idx[np.argmax(reduction)])  # the largest reduction leaves the smallest joint distance
        b = slice(3 * best, 3 * best + 3)
        # inverse of the kept sub-matrix from the full inverse (downdate in place, O(k^2))
        Y -= Y[:, b] @ np.linalg.solve(Y[b, b], Y[b, :])
        Y[b, :] = 0.0
        Y[:, b] = 0.0
        nu[b] = 0.0
        kept[best] = False
        n_dropped += 1
    return det[kept], cand[kept], n_dropped


def _cho_inverse(L: np.ndarray) -> np.ndarray:
    """The inverse (symmetric, full) of ``L L^T`` from ``cho_factor``'s lower factor ``L`` (LAPACK
    potri: half the work of solving against the identity)."""
    inv, info = potri(L, lower=1)
    if info != 0:
        raise LinAlgError(f"potri failed (info {info})")
    return np.where(_lower_mask(inv.shape[0]), inv, inv.T)  # potri fills the lower triangle only


@functools.lru_cache(maxsize=64)
def _lower_mask(n: int) -> np.ndarray:
    """(n, n) bool: the lower triangle with the diagonal (cached: numpy's tril builds it per call)."""
    return np.tri(n, dtype=bool)


def _kept_inverse(S: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Full-size inverse of the sub-matrix of ``S`` (3k, 3k) on the ``kept`` (k,) pairs' blocks,
    zero on the others: by Cholesky, or floored (:func:`_pd_inverse`) where that fails."""
    rows = np.flatnonzero(np.repeat(kept, 3))
    sub = S[np.ix_(rows, rows)]
    try:
        inv = _cho_inverse(cho_factor(sub, lower=True, check_finite=False)[0])
    except LinAlgError:
        inv = _pd_inverse(sub)
    Y = np.zeros_like(S)
    Y[np.ix_(rows, rows)] = inv
    return Y


def _dedupe_new(is_new: np.ndarray, z_base: np.ndarray, R_z: np.ndarray, gate_chi2: float) -> np.ndarray:
    """Two new detections of one frame compatible with each other are one rock: keep the nearer one."""
    idx = np.flatnonzero(is_new)
    if idx.size < 2:
        return is_new
    order = idx[np.argsort(np.linalg.norm(z_base[idx], axis=1))]
    d2 = pairwise_d2(z_base[order], R_z[order], z_base[order], R_z[order], gate_chi2)
    out = is_new.copy()
    kept: list[int] = []
    for a in range(order.size):
        if any(d2[a, b] < gate_chi2 for b in kept):
            out[order[a]] = False
        else:
            kept.append(a)
    return out

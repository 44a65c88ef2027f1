"""The crater kind's observation, and the rim-fit model behind its covariance.

A crater is seen by the rover's stereo as points on its rim. Its observation is the rim's centre
in base_link (the centre of the rim circle at the rim's mean height) with a 3x3 covariance, the
rim diameter with its sigma, the fraction of the rim that was seen and a score.

Where the covariance comes from (:func:`rim_fit_covariance`): a least-squares circle fit of rim
points ``p_i = c + r (cos a_i, sin a_i)`` with horizontal sigma ``sigma_i`` has the Fisher
information ``sum_i J_i^T J_i / sigma_i^2`` with ``J_i = (cos a_i, sin a_i, 1)`` over
``(cx, cy, r)``. A whole rim fixes the centre to ``sigma sqrt(2/N)`` and the radius to
``sigma / sqrt(N)``, uncorrelated. A partial rim (a crater larger than the view, or half of it
out of range) sees the points on an arc only: along the arc's axis of symmetry the centre and the
radius trade off (moving the centre towards the arc and shrinking the radius fits the arc almost
as well), so the centre variance along that axis and the radius variance grow together, steeply
as the arc shortens (about as the inverse fourth power of the arc's half angle), while across the
axis the centre stays well placed. Rim irregularity (real rims are not circles) adds
``(irregularity_frac D)^2`` to every point. The covariance is the inverse of that information;
the sensor model (``sim.sensors.craters``) and a stereo rim fit (:func:`fit_rim`) both use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.errors import MeasurementError
from reloc.measurements import _array, _time

MIN_RIM_POINTS = 3  # a circle needs three points


@dataclass(frozen=True, slots=True)
class CraterObservations:
    """One stereo frame of crater rims at ``t`` (possibly empty, N = 0).

    ``xyz_base_m`` (N, 3): rim centres in base_link; ``cov_base_m2`` (N, 3, 3) their covariance
    (see module doc: long along the axis of a partial rim); ``size_m`` (N,): rim diameters;
    ``size_sigma_m`` (N,): their 1-sigma; ``completeness`` (N,) in (0, 1]: the fraction of the
    rim seen; ``score`` (N,) in [0, 1]: detector confidence."""

    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray
    size_m: np.ndarray
    size_sigma_m: np.ndarray
    completeness: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("CraterObservations.t", self.t))
        xyz = _array("CraterObservations.xyz_base_m", np.reshape(self.xyz_base_m, (-1, 3)), (None, 3))
        n = xyz.shape[0]
        cov = _array("CraterObservations.cov_base_m2", np.reshape(self.cov_base_m2, (-1, 3, 3)), (n, 3, 3))
        vec = {name: _array(f"CraterObservations.{name}", np.reshape(getattr(self, name), (-1,)), (n,))
               for name in ("size_m", "size_sigma_m", "completeness", "score")}
        if n and np.any(np.abs(cov - np.swapaxes(cov, 1, 2)) > 1e-9 * (1.0 + np.abs(cov))):
            raise MeasurementError("CraterObservations.cov_base_m2 must be symmetric")
        if n and np.any(np.linalg.eigvalsh(cov)[:, 0] <= 0.0):
            raise MeasurementError("CraterObservations.cov_base_m2 must be positive definite")
        if np.any(vec["size_m"] <= 0.0) or np.any(vec["size_sigma_m"] <= 0.0):
            raise MeasurementError("CraterObservations.size_m and size_sigma_m must be positive")
        c = vec["completeness"]
        if np.any((c <= 0.0) | (c > 1.0)):
            raise MeasurementError(f"CraterObservations.completeness must be in (0, 1], got {c[(c <= 0) | (c > 1)][:3]}")
        if np.any((vec["score"] < 0.0) | (vec["score"] > 1.0)):
            raise MeasurementError("CraterObservations.score must be in [0, 1]")
        object.__setattr__(self, "xyz_base_m", xyz)
        object.__setattr__(self, "cov_base_m2", cov)
        for name, value in vec.items():
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.xyz_base_m.shape[0])


@dataclass(frozen=True)
class RimFit:
    """A circle fitted to rim points: ``centre_m`` (2,) horizontal, ``radius_m``, their joint
    covariance ``cov`` (3, 3) over (cx, cy, r), and ``arc_fraction`` the share of the circle the
    points cover (their largest angular gap left out)."""

    centre_m: np.ndarray
    radius_m: float
    cov: np.ndarray
    arc_fraction: float


def rim_fit_covariance(angles_rad: np.ndarray, sigma_m: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of (cx, cy, r) of a circle fit to points at rim angles ``angles_rad``
    (N,) with horizontal sigmas ``sigma_m`` (N,) or scalar (m); see module doc."""
    a = np.reshape(np.asarray(angles_rad, dtype=float), (-1,))
    if a.size < MIN_RIM_POINTS:
        raise MeasurementError(f"a rim fit needs at least {MIN_RIM_POINTS} points, got {a.size}")
    w = 1.0 / np.broadcast_to(np.asarray(sigma_m, dtype=float), a.shape) ** 2
    J = np.stack([np.cos(a), np.sin(a), np.ones_like(a)], axis=1)
    info = (J * w[:, None]).T @ J
    return np.linalg.inv(info)


def arc_fraction(angles_rad: np.ndarray) -> float:
    """Share of the circle covered by points at ``angles_rad`` (N,): one minus the largest gap."""
    a = np.sort(np.mod(np.reshape(np.asarray(angles_rad, dtype=float), (-1,)), 2 * np.pi))
    if a.size == 0:
        return 0.0
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * np.pi]]))
    return float(1.0 - gaps.max() / (2 * np.pi))


def fit_rim(xy_m: np.ndarray, sigma_m: np.ndarray | float) -> RimFit:
    """Fit a circle to horizontal rim points ``xy_m`` (N, 2) m with sigmas ``sigma_m`` (N,) or
    scalar: algebraic (Kasa) start, then Gauss-Newton on the geometric distances; the covariance
    is :func:`rim_fit_covariance` at the fitted angles (the stereo image path's rim fit)."""
    xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
    if len(xy) < MIN_RIM_POINTS or not np.all(np.isfinite(xy)):
        raise MeasurementError(f"a rim fit needs at least {MIN_RIM_POINTS} finite points, got {len(xy)}")
    sig = np.broadcast_to(np.asarray(sigma_m, dtype=float), (len(xy),))
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, np.sum(xy * xy, axis=1), rcond=None)
    c = sol[:2]
    r = float(np.sqrt(max(sol[2] + c @ c, 1e-12)))
    w = 1.0 / sig
    for _ in range(10):
        d = xy - c
        rho = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        u = d / rho[:, None]
        res = (rho - r) * w
        J = np.column_stack([-u, -np.ones(len(xy))]) * w[:, None]
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        c, r = c + step[:2], r + float(step[2])
        if np.linalg.norm(step) < 1e-9 * max(r, 1.0):
            break
    if not (np.isfinite(r) and r > 0):
        raise MeasurementError("rim points do not fit a circle")
    ang = np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0])
    return RimFit(c, r, rim_fit_covariance(ang, sig), arc_fraction(ang))

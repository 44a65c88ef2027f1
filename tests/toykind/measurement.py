"""The cairn kind's observation: one stereo frame of cairn detections (toy kind, see package doc)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.errors import MeasurementError


@dataclass(frozen=True, slots=True)
class CairnObservations:
    """Cairns at ``t``: centres ``xyz_base_m`` (N, 3) in base_link, covariances ``cov_base_m2``
    (N, 3, 3), heights ``size_m`` (N,)."""

    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray
    size_m: np.ndarray

    def __post_init__(self) -> None:
        xyz = np.array(self.xyz_base_m, dtype=float).reshape(-1, 3)
        n = xyz.shape[0]
        cov = np.array(self.cov_base_m2, dtype=float).reshape(n, 3, 3)
        size = np.array(self.size_m, dtype=float).reshape(n)
        if not (np.isfinite(self.t) and np.isfinite(xyz).all() and np.isfinite(cov).all() and np.isfinite(size).all()):
            raise MeasurementError(f"CairnObservations at t={self.t} contains NaN or inf")
        if n and np.any(np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2)))[:, 0] <= 0):
            raise MeasurementError("CairnObservations.cov_base_m2 must be positive definite")
        for name, value in (("t", float(self.t)), ("xyz_base_m", xyz), ("cov_base_m2", cov), ("size_m", size)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.xyz_base_m.shape[0])

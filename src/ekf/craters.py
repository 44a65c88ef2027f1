"""The crater kind's EKF layer: rim centres as 3D points of the shared landmark block.

A crater rim's centre, measured in base_link with its covariance (:mod:`reloc.craters`: long
along the axis of a partial rim), has the rock's measurement model ``h = R^T (l - p)`` (and the
stereo calibration's correction when the filter estimates it), so the update is the rock kind's
(:class:`ekf.rocks.RockUpdate`: candidates, joint-compatibility association, the frame budget, one
stacked Joseph update, initialisation with cross covariances) run with the crater settings of
:class:`CraterEkfConfig`: craters are seen farther than rocks, their diameters are measured well
(a tighter diameter-ratio gate), and they come at their own rate. Only crater landmarks are
candidates (the landmark book's kind code); hygiene and the bound on the state stay the filter's.
The history replay after a late fix calls :meth:`update` again with ``count`` False.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ekf.config import EkfConfig
from ekf.errors import EkfInputError
from ekf.kinds import kind_config
from ekf.rocks import RockUpdate
from reloc.association import AssociationConfig
from reloc.backend import LandmarkUpdateReport
from reloc.budget import ObservationBudget
from reloc.config import NonNegative, NonNegativeInt, Positive
from reloc.craters import CraterObservations
from reloc.errors import ConfigError
from reloc.kinds import LandmarkKind


@dataclass(frozen=True)
class CraterEkfConfig:
    """The crater update's settings (``EkfConfig.kinds["craters"]``)."""

    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(
        max_range_m=30.0, max_size_ratio=1.6, persistence_s=0.0))  # rims are fitted out to 25 m; diameters to ~10 %
    cov_scale: Positive = 1.0  # the reported rim-centre covariance is multiplied by this
    period_s: NonNegative = 1.0  # crater frames closer than this to the last used one are skipped
    candidate_margin_m: NonNegative = 5.0
    budget: ObservationBudget = field(default_factory=lambda: ObservationBudget(max_observations=10, max_new=0))
    skip_lone_ambiguous_pair: bool = True
    use: bool = True  # False: crater frames are counted and left out (a rocks-only run of the same stream)
    # slots of the state's bound (EkfConfig.max_landmarks) that rocks may not take once a crater
    # frame has come: rocks come 5 x as often and in tens, and took every slot on rocky-1km
    reserved_landmarks: NonNegativeInt = 20


class CraterUpdate(RockUpdate):
    """The crater kind's update (see module doc); counters are prefixed ``crater_``."""

    config_class = CraterEkfConfig

    def __init__(self, config: EkfConfig, kind: LandmarkKind) -> None:
        c = kind_config(type(self), kind, config)
        super().__init__(dataclasses.replace(
            config, association=c.association, rock_cov_scale=c.cov_scale, landmark_period_s=c.period_s,
            candidate_margin_m=c.candidate_margin_m, budget=c.budget,
            skip_lone_ambiguous_pair=c.skip_lone_ambiguous_pair), kind)
        self.crater_config = c
        if c.reserved_landmarks > config.max_landmarks:
            raise ConfigError(f"ekf.kinds.craters.reserved_landmarks ({c.reserved_landmarks}) exceeds "
                              f"max_landmarks ({config.max_landmarks})")
        self.reserved = c.reserved_landmarks
        self.counts = {f"crater_{k}": v for k, v in self.counts.items()}

    def _bump(self, count: bool, **kw: int) -> None:
        super()._bump(count, **{f"crater_{k}": v for k, v in kw.items()})

    def update(self, s, obs: CraterObservations, count: bool = True) -> LandmarkUpdateReport:
        """The rock update with the crater settings (see module doc); nothing when ``use`` is off."""
        if not self.crater_config.use:
            self._bump(count, n_frames_skipped=1)
            return LandmarkUpdateReport(obs.t, len(obs), 0, 0, len(obs))
        return super().update(s, obs, count)

    def check(self, obs: CraterObservations) -> None:
        """Finite, consistently shaped arrays (the filter checks the time order)."""
        arrays = (obs.xyz_base_m, obs.cov_base_m2, obs.size_m, obs.size_sigma_m, obs.completeness)
        if not math.isfinite(obs.t) or not all(np.all(np.isfinite(a)) for a in arrays):
            raise EkfInputError(f"CraterObservations at t={obs.t} contains NaN or inf")
        n = len(obs)
        if obs.xyz_base_m.shape != (n, 3) or obs.cov_base_m2.shape != (n, 3, 3) or obs.size_m.shape != (n,):
            raise EkfInputError("CraterObservations arrays have inconsistent shapes")

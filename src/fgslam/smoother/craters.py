"""The crater kind's smoother layer: rim centres as Point3 variables ``R(j)`` (key symbol ``r``).

A crater rim's centre is a point seen in base_link, so its factor is the rock's C++
``BearingRangeFactor3D`` (or the calibrated point factor when the smoother estimates the stereo
calibration and ``share_calibration`` is on, the default; off, the calibration's prior is
considered in its covariance) whose bearing/range covariance is the exact linear image of the rim centre's
covariance (:func:`fgslam.smoother.factors.make_point_factor`): a partial rim's long axis stays
long. Association, candidates, the per-frame budget and fixed-lag retirement are the rock
layer's (:class:`fgslam.smoother.rocks.RockLandmarks`), run with the crater settings of
:class:`CraterSmootherConfig` (``SmootherConfig.kinds["craters"]``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from fgslam.smoother.kinds import kind_config
from fgslam.smoother.landmarks import LandmarkStore
from fgslam.smoother.rocks import RockLandmarks, considered_calibration_cov
from reloc.association import AssociationConfig
from reloc.backend import LandmarkUpdateReport
from reloc.budget import ObservationBudget
from reloc.config import NonNegative, Positive, PositiveInt
from reloc.kinds import LandmarkKind


@dataclass(frozen=True)
class CraterSmootherConfig:
    """The crater layer's settings; the rest of the landmark settings are the rocks'."""

    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(
        max_range_m=30.0, max_size_ratio=1.6, persistence_s=0.0))
    min_obs_to_insert: PositiveInt = 2  # observations (on distinct keyframes) before a crater enters the graph
    candidate_timeout_s: Positive = 30.0  # craters come at 0.5 Hz: a longer wait than a rock's
    huber_k: Positive = 3.0
    cov_scale: Positive = 1.0  # the reported rim-centre covariance is multiplied by this
    min_frame_interval_s: NonNegative = 0.95
    budget: ObservationBudget = field(default_factory=lambda: ObservationBudget(max_observations=10, max_new=3))
    use: bool = True  # False: crater frames are counted and left out (a rocks-only run of the same stream)
    # with the calibration variable C(0) (calibration_mode "estimate"): whether crater factors
    # share it (calibrated CustomFactors, the same stereo) or take its prior into their covariance
    # (C++ factors, as "consider"). First 400 m, no fixes: shared, sparse-5km's range scale ran to
    # 1.012-1.016 (true 0.9971; rocks alone 1.0047); considered, craters claim an exact scale and pin
    # it at 1.000 +- 0.0003 (rocky-1km, cratered-3km). docs/smoother.md, "Long traverses"
    share_calibration: bool = True


class CraterLandmarks(RockLandmarks):
    """Craters in the smoother (see module doc)."""

    config_class = CraterSmootherConfig

    def __init__(self, config, kind: LandmarkKind, calib_key: int | None) -> None:
        c = kind_config(type(self), kind, config)
        super().__init__(config, kind, calib_key if c.share_calibration else None)
        if calib_key is not None and not c.share_calibration:  # the calibration's prior considered
            self._consider_cov = considered_calibration_cov(config)
        self.crater_config = c
        self.cfg = dataclasses.replace(
            config.landmarks, association=c.association, min_obs_to_insert=c.min_obs_to_insert,
            candidate_timeout_s=c.candidate_timeout_s, huber_k=c.huber_k, rock_cov_scale=c.cov_scale,
            min_frame_interval_s=c.min_frame_interval_s, budget=c.budget)
        self.store = LandmarkStore(self.cfg)

    def observe(self, obs, frame) -> LandmarkUpdateReport:
        """The rock layer's association and factors with the crater settings; nothing when ``use`` is off."""
        if not self.crater_config.use:
            self.n_frames_skipped += 1
            return LandmarkUpdateReport(obs.t, len(obs), 0, 0, len(obs))
        return super().observe(obs, frame)

    def stats(self) -> dict:
        return {f"crater_{k}": v for k, v in super().stats().items()}

"""The wrong-fix fault (``faults.wrong_fixes`` of a simulator config): a relocalizer that lies.

A bag holds no fixes, so a burst of wrong fixes cannot come from the simulator: it is injected
where fixes are made. :class:`WrongFixes` wraps a relocalizer (:class:`fgslam.fix_sources.FixProducer`)
and replaces every fix whose ``t_meas`` falls in the fault window (or a seeded ``fraction`` of
them) by one moved ``offset_m`` (or a distance uniform up to ``offset_max_m``) in a seeded random
direction and turned by ``+-yaw_deg`` (random sign), keeping the match's claimed
covariance, inliers and RMSE: a confidently wrong match, which is what a repetitive rock field or
a wrong catalog would give. A comparison computes its fixes once in the reference pass, so every
back-end with relocalization receives the same wrong fixes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from fgslam.fix_sources import FixProducer, WrappedProducer
from fgslam.relocalizer import FixAttempt
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.geometry import wrap_angle

SEED_STREAM = 300  # rng stream of the wrong fixes: default_rng([seed, SEED_STREAM])


class WrongFixes(WrappedProducer):
    """``inner``'s fixes, wrong inside ``window`` = [start, end) (s, absolute stream time)."""

    def __init__(self, inner: FixProducer, fault, window: tuple[float, float], seed: int) -> None:
        super().__init__(inner)
        self.fault = fault
        self.window = (float(window[0]), float(window[1]))
        self._rng = np.random.default_rng([int(seed), SEED_STREAM])
        self.n_wrong = 0

    def attempt(self, maps: Mapping[str, LandmarkMap], est: PoseEstimate) -> FixAttempt:
        att = self.inner.attempt(maps, est)
        fix = att.fix
        if fix is None or not self.window[0] <= fix.t_meas < self.window[1]:
            return att
        # one draw per fix in the window, used or not, so the wrong ones are the same for a seed
        u, bearing, flip, r = self._rng.random(), self._rng.uniform(-np.pi, np.pi), self._rng.random(), self._rng.random()
        if u >= self.fault.fraction:
            return att
        sign = 1.0 if flip < 0.5 else -1.0
        hi = self.fault.offset_max_m
        offset = self.fault.offset_m if hi is None else self.fault.offset_m + r * (hi - self.fault.offset_m)
        wrong = dataclasses.replace(
            fix,
            x_m=fix.x_m + offset * np.cos(bearing),
            y_m=fix.y_m + offset * np.sin(bearing),
            yaw_rad=float(wrap_angle(fix.yaw_rad + sign * np.deg2rad(self.fault.yaw_deg))),
            height=None,  # a height read at the right place would tell the wrong fix apart: none
            anchors=(),  # a wrong pose, not the right landmarks' entries
        )
        self.n_wrong += 1
        return dataclasses.replace(att, fix=wrong, tracked=False)


def with_wrong_fixes(relocalizers: list[FixProducer], fault, window: tuple[float, float], seed: int) -> list[FixProducer]:
    """``relocalizers`` each wrapped by :class:`WrongFixes` (one seeded stream per relocalizer)."""
    return [WrongFixes(r, fault, window, seed + 1000 * i) for i, r in enumerate(relocalizers)]

"""The wrong-fix fault: a relocalizer wrapper that moves the fixes of its window, seeded."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.bench.faults import recovery_s
from fgslam.fault_fixes import with_wrong_fixes
from fgslam.relocalizer import FixAttempt
from reloc.backend import PoseEstimate
from reloc.measurements import GlobalFix
from sim.faults import WrongFixesConfig


class _Exact:
    """A relocalizer that always returns the estimate's pose as its fix."""

    kinds = ("rocks",)
    period_s = 2.0
    config = None
    build_time_s = 0.0

    def wants(self, est):
        return True

    def attempt(self, maps, est):
        fix = GlobalFix(est.t, est.t + 0.5, 1.0, 2.0, 0.3, np.diag([0.01, 0.01, 1e-4]), 12, 0.02)
        return FixAttempt(est.t, 40, "fix", 0.01, fix=fix, tracked=True)


def _est(t):
    return PoseEstimate(t=t, T_world_base=np.eye(4), cov=np.eye(6) * 1e-4)


def test_wrong_fixes_only_inside_the_window_offset_and_seeded():
    fault = WrongFixesConfig(offset_m=3.0, yaw_deg=10.0)
    runs = []
    for _ in range(2):
        (r,) = with_wrong_fixes([_Exact()], fault, (10.0, 20.0), seed=4)
        runs.append([r.attempt({}, _est(t)) for t in np.arange(0.0, 30.0, 2.0)])
    for a, b in zip(*runs):
        assert a.fix.xyyaw.tolist() == b.fix.xyyaw.tolist()  # seeded
    for att in runs[0]:
        d = np.hypot(att.fix.x_m - 1.0, att.fix.y_m - 2.0)
        if 10.0 <= att.t_meas < 20.0:
            assert d == pytest.approx(3.0) and abs(att.fix.yaw_rad - 0.3) == pytest.approx(np.deg2rad(10.0))
            assert not att.tracked
            np.testing.assert_array_equal(att.fix.cov_xyyaw, np.diag([0.01, 0.01, 1e-4]))  # claimed as good
        else:
            assert d == 0.0 and att.fix.yaw_rad == 0.3 and att.tracked
    bearings = {round(float(np.arctan2(a.fix.y_m - 2.0, a.fix.x_m - 1.0)), 6) for a in runs[0] if 10 <= a.t_meas < 20}
    assert len(bearings) == 5


def test_a_fraction_of_the_fixes_wrong_with_offsets_in_a_range():
    fault = WrongFixesConfig(start_s=0.0, duration_s=None, offset_m=5.0, offset_max_m=50.0, fraction=0.2)
    (r,) = with_wrong_fixes([_Exact()], fault, (0.0, np.inf), seed=7)
    atts = [r.attempt({}, _est(t)) for t in np.arange(0.0, 4000.0, 2.0)]
    d = np.array([np.hypot(a.fix.x_m - 1.0, a.fix.y_m - 2.0) for a in atts])
    wrong = d > 0
    assert r.n_wrong == int(wrong.sum())
    n = len(atts)  # 2000 fixes: the share within 4 binomial sigma of 20 %
    assert abs(wrong.mean() - 0.2) < 4 * np.sqrt(0.2 * 0.8 / n)
    assert d[wrong].min() >= 5.0 and d[wrong].max() <= 50.0
    assert abs(np.median(d[wrong]) - 27.5) < 3.0  # uniform in [5, 50]
    assert all(a.tracked for a, w in zip(atts, wrong) if not w)


def test_wrong_fix_settings_are_checked():
    from sim.faults import FaultConfigError

    with pytest.raises(FaultConfigError, match="fraction"):
        WrongFixesConfig(fraction=0.0)
    with pytest.raises(FaultConfigError, match="offset_max_m"):
        WrongFixesConfig(offset_m=10.0, offset_max_m=5.0)


def test_recovery_time():
    t = np.arange(10.0)
    err = np.array([0.1, 0.1, 0.5, 0.5, 0.3, 0.1, 0.3, 0.1, 0.1, 0.1])
    assert recovery_s(t, err, 4.0, 0.2) == 3.0  # last above at t=6, below from t=7
    assert recovery_s(t, err, 7.0, 0.2) == 0.0
    assert recovery_s(t, np.r_[err[:-1], 0.5], 4.0, 0.2) is None


class _NoMatch:
    """A matcher that never matches (counts its calls)."""

    def __init__(self) -> None:
        self.calls = 0

    def match(self, *args):
        self.calls += 1


def test_relocalizer_skips_a_map_without_new_observations():
    from fgslam.relocalizer import Relocalizer
    from reloc.backend import LandmarkMap
    from reloc.measurements import RockCatalog

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (20, 2))
    cat = RockCatalog(xy, np.full(20, 0.5), np.ones(20))
    matcher = _NoMatch()
    reloc = Relocalizer(cat, {"min_new_observations": 3, "single_landmark": False}, matcher=matcher)

    def lmap(n_obs):
        return LandmarkMap(np.arange(20), np.column_stack([xy, np.zeros(20)]), np.tile(np.eye(3) * 1e-4, (20, 1, 1)),
                           np.full(20, 0.5), np.asarray(n_obs), "rocks")

    base = np.full(20, 5)
    assert reloc.attempt(lmap(base), _est(0.0)).status == "no match"  # the first attempt always runs
    assert reloc.attempt(lmap(base), _est(2.0)).status == "stale map"  # camera blind: nothing new
    assert reloc.attempt(lmap(base + (np.arange(20) < 2)), _est(4.0)).status == "stale map"  # 2 < 3
    assert reloc.attempt(lmap(base + (np.arange(20) < 5)), _est(6.0)).status == "no match"
    assert matcher.calls == 2
    off = Relocalizer(cat, {"min_new_observations": 0, "single_landmark": False}, matcher=_NoMatch())
    assert [off.attempt(lmap(base), _est(t)).status for t in (0.0, 2.0)] == ["no match", "no match"]

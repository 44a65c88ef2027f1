"""The back-end contract, checked against every registered back-end (EKF, iSAM2, dead reckoning):
the protocol, time order, late fixes, unknown kinds, landmark maps by kind, the resolved config's
round trip, and a runner that consumes any stream lazily."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from _synth_stream import make_stream

from ekf.errors import EkfError
from fgslam.backends.registry import (
    BACKEND_NAMES,
    backend_config_dict,
    make_backend,
    resolved_config,
)
from fgslam.errors import FgslamError
from fgslam.inputs import truth_of
from fgslam.runner import RunnerError, run_backend
from reloc.backend import Backend, LandmarkMap, PoseEstimate
from reloc.craters import CraterObservations
from reloc.errors import RelocError
from reloc.kinds import LandmarkKind, registered
from reloc.measurements import GlobalFix, ImuSample, RockObservations
from reloc.odometry import OdometryStep

OVERRIDES = {"dr": {"use_fixes": True}}  # dead reckoning applies fixes only when told to
PACKAGE_ERRORS = (FgslamError, EkfError, RelocError)


@dataclasses.dataclass(frozen=True)
class Pebbles:
    """A landmark observation of a kind registered without back-end layers (see the tests below)."""

    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray
    size_m: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz_base_m)


class Unregistered(Pebbles):
    """Looks like an observation, but no kind is registered for it."""


PEBBLES = LandmarkKind(name="pebbles", measurement=Pebbles, rank=9, symbol="p")


def _obs(cls, t: float):
    return cls(t, np.array([[3.0, 0.5, 0.0]]), np.eye(3)[None] * 0.01, np.array([0.2]))


@pytest.fixture(scope="module")
def stream():
    return make_stream(seed=21, duration_s=30.0, craters=True)  # rocks and craters, the registered kinds


@pytest.fixture(scope="module", params=BACKEND_NAMES)
def ran(request, stream):
    name = request.param
    be = make_backend(name, stream.initial, OVERRIDES.get(name))
    return name, be, run_backend(be, stream.measurements)


def _offset_start(stream, dx: float = 0.5) -> PoseEstimate:
    T = stream.initial.T_world_base.copy()
    T[0, 3] += dx
    return PoseEstimate(stream.initial.t, T, np.diag([0.3**2, 0.3**2, 0.01**2, 1e-6, 1e-6, 1e-4]))


def _truth_fix(gt, t_meas: float, t_recv: float, dx: float = 0.0) -> GlobalFix:
    T = gt.T_world_base[min(int(np.searchsorted(gt.t, t_meas)), len(gt.t) - 1)]
    return GlobalFix(t_meas, t_recv, T[0, 3] + dx, T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])), np.diag([0.15**2, 0.15**2, 0.01**2]))


def test_implements_the_protocol(ran):
    name, be, res = ran
    assert isinstance(be, Backend) and be.name == res.backend == name
    assert backend_config_dict(be) == resolved_config(name, OVERRIDES.get(name))
    be.expect_fix(res.t_end)  # a capability every back-end has (a no-op where nothing rolls back)


def test_time_order(ran, stream):
    _, be, res = ran
    est = be.estimate()
    assert est.t == pytest.approx(res.t_end, abs=0.05)
    for traj in (res.final, res.online):
        assert np.all(np.diff(traj.t) > 0)
    # a step from the past never moves the estimate back: refused, or ignored
    R = np.eye(3)
    stale = OdometryStep(1.0, 1.1, 0.2, 0.0, R, R, np.zeros(3))
    try:
        be.predict(stale)
    except PACKAGE_ERRORS as exc:
        assert "order" in str(exc) or "before" in str(exc)
    after = be.estimate()
    assert after.t == est.t and np.array_equal(after.T_world_base, est.T_world_base)


@pytest.mark.parametrize("name", BACKEND_NAMES)
def test_a_late_fix_lands_at_its_measurement_time(stream, name):
    """Started 0.5 m off, a fix from truth for t_meas 6 s in the past pulls the current estimate
    onto the truth; fixes from the future, from before the start or far off are refused with a
    reason, never raised."""
    gt = truth_of(stream)
    be = make_backend(name, _offset_start(stream), OVERRIDES.get(name))
    res = run_backend(be, stream.measurements)
    t_now = be.estimate().t

    def err() -> float:
        e = be.estimate()
        k = min(int(np.searchsorted(gt.t, e.t)), len(gt.t) - 1)
        return float(np.linalg.norm(e.position_m[:2] - gt.positions_m[k, :2]))

    before = err()
    assert before > 0.3
    ahead = be.apply_fix(_truth_fix(gt, t_now + 5.0, t_now + 5.0))
    ancient = be.apply_fix(GlobalFix(res.t_start - 50.0, t_now, 0.0, 0.0, 0.0, np.eye(3) * 1e-3))
    assert not ahead.accepted and "ahead" in ahead.reason
    assert not ancient.accepted and ancient.reason
    late = be.apply_fix(_truth_fix(gt, t_now - 6.0, t_now))
    assert late.accepted, late.reason
    assert err() < 0.5 * before
    if name != "dr":  # the SLAM back-ends gate a fix 40 m off (dead reckoning trusts any fix it is given)
        far = be.apply_fix(_truth_fix(gt, t_now - 4.0, t_now, dx=40.0))
        assert not far.accepted and "gate" in far.reason


def test_unknown_kinds_are_refused(ran):
    _, be, _ = ran
    with pytest.raises(PACKAGE_ERRORS, match="Unregistered"):
        be.observe(_obs(Unregistered, be.estimate().t + 0.01))
    with pytest.raises(PACKAGE_ERRORS, match="no_such_kind"):
        be.landmark_map("no_such_kind")


def test_the_runner_refuses_unknown_kinds(stream):
    meas = [*stream.measurements[:50], _obs(Unregistered, stream.measurements[50].t), *stream.measurements[51:60]]
    with pytest.raises(RunnerError, match="Unregistered is not the observation of any registered landmark kind"):
        run_backend(make_backend("ekf", stream.initial), meas)


def test_landmark_maps_by_kind(ran):
    _, be, res = ran
    assert list(res.landmarks) == ["rocks", "craters"]
    for kind, least in (("rocks", 10), ("craters", 3)):
        lm = be.landmark_map(kind)
        assert lm.kind == kind and len(lm) >= least, (kind, len(lm))
        n = len(lm)
        assert lm.xyz_world_m.shape == (n, 3) and lm.cov_world_m2.shape == (n, 3, 3)
        assert lm.size_m.shape == (n,) and lm.n_obs.shape == (n,) and len(np.unique(lm.ids)) == n
        assert np.all(np.linalg.eigvalsh(lm.cov_world_m2) > 0)
        assert res.landmarks[kind].kind == kind
    # craters (2-8 m) are mapped as craters, never mixed with the rocks (< 1.5 m)
    assert np.all(be.landmark_map("craters").size_m > 1.5) and np.all(be.landmark_map("rocks").size_m < 2.0)
    with registered(PEBBLES):  # a registered kind never observed: an empty map of that kind
        empty = be.landmark_map("pebbles")
        assert isinstance(empty, LandmarkMap) and empty.kind == "pebbles" and len(empty) == 0


def test_a_kind_without_the_backends_layer_is_refused(stream):
    with registered(PEBBLES):
        for name in ("ekf", "isam2"):
            with pytest.raises(PACKAGE_ERRORS, match=f"kind 'pebbles' has no {'ekf' if name == 'ekf' else 'smoother'} layer"):
                make_backend(name, stream.initial).observe(_obs(Pebbles, stream.initial.t + 0.1))
        dr = make_backend("dr", stream.initial)  # dead reckoning maps any kind's points
        dr.observe(_obs(Pebbles, stream.initial.t + 0.1))
        assert len(dr.landmark_map("pebbles")) == 1 and len(dr.landmark_map("rocks")) == 0


def test_the_resolved_config_round_trips(ran, stream):
    name, be, _ = ran
    saved = yaml.safe_load(yaml.safe_dump(backend_config_dict(be), sort_keys=False))
    again = make_backend(name, stream.initial, saved)
    assert backend_config_dict(again) == saved
    assert type(again.config) is type(be.config)
    # the saved config names every registered kind's resolved settings (craters' defaults), the
    # original only its overrides: the two resolve alike
    if hasattr(be.config, "kinds"):
        assert dataclasses.replace(again.config, kinds={}) == dataclasses.replace(be.config, kinds={})
        assert set(again.config.kinds) == {k for k in ("craters",) if k in saved["kinds"]} | set(be.config.kinds)
    else:
        assert again.config == be.config


@pytest.mark.parametrize("name", BACKEND_NAMES)
def test_the_runner_consumes_the_stream_lazily(stream, name):
    """A generator, pulled one measurement at a time: every back-end call happens before the next
    measurement is read (no look-ahead, no list, no len)."""
    pulled = {"n": 0}

    def gen():
        for m in stream.measurements:
            pulled["n"] += 1
            yield m

    class Watch(Backend):
        def __init__(self, inner):
            self.inner, self.name, self.config, self.calls = inner, inner.name, inner.config, []

        def predict(self, step):
            self.calls.append((ImuSample, step.t1, pulled["n"]))
            return self.inner.predict(step)

        def observe(self, obs):
            self.calls.append((type(obs), obs.t, pulled["n"]))
            return self.inner.observe(obs)

        def apply_fix(self, fix):
            return self.inner.apply_fix(fix)

        def estimate(self):
            return self.inner.estimate()

        def landmark_map(self, kind):
            return self.inner.landmark_map(kind)

        def trajectory(self):
            return self.inner.trajectory()

        def stats(self):
            return self.inner.stats()

    be = Watch(make_backend(name, stream.initial))
    res = run_backend(be, gen())
    by_t = {}
    for i, m in enumerate(stream.measurements):
        if isinstance(m, (ImuSample, RockObservations, CraterObservations)):
            by_t.setdefault((type(m), m.t), i)
    for kind, t, n in be.calls:  # the measurement that triggered the call was the last one pulled
        assert n == by_t[(kind, t)] + 1
    assert any(kind is CraterObservations for kind, _, _ in be.calls)
    assert pulled["n"] == len(stream.measurements) and len(res.online) > 0

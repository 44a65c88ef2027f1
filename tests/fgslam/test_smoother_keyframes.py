"""The smoother's keyframe store: times as one growing array, causal and frozen poses as rows."""

from __future__ import annotations

import bisect

import numpy as np
import pytest

from fgslam.smoother.keyframes import KeyframeStore


def _pose(i: float) -> tuple[np.ndarray, np.ndarray]:
    T = np.eye(4)
    T[:3, 3] = [i, -i, 0.5 * i]
    c = np.arange(36.0).reshape(6, 6) + i
    return T, c @ c.T


def test_a_thousand_keyframes_keep_their_times_poses_and_frozen_estimates():
    kfs = KeyframeStore()
    times = np.cumsum(np.random.default_rng(0).uniform(0.2, 1.5, 1000))
    for i, t in enumerate(times):  # past the first allocations of times and rows
        assert kfs.add(t) == i
        kfs.record_online(*_pose(i))
        if i % 3 == 0 and i > 10:
            kfs.freeze(i - 10, *_pose(-i))
    assert len(kfs) == kfs.n_online == 1000
    np.testing.assert_array_equal(kfs.t, times)
    for i in (0, 255, 256, 511, 999):
        T, C = _pose(i)
        np.testing.assert_array_equal(kfs.online_T(i), T)
        np.testing.assert_array_equal(kfs.online_cov(i), C)
    for q in (times[0] - 1.0, times[0], times[417] + 1e-6, times[-1] + 5.0):
        assert kfs.before(q) == bisect.bisect_right(list(times), q) - 1
    assert kfs.is_frozen(2) and not kfs.is_frozen(3)
    T, C = kfs.frozen(2)
    np.testing.assert_array_equal(T, _pose(-12)[0])
    np.testing.assert_array_equal(C, _pose(-12)[1])
    with pytest.raises(KeyError):
        kfs.frozen(3)
    t, Ts, Cs = kfs.online_arrays()
    np.testing.assert_array_equal(t, times)
    np.testing.assert_array_equal(Ts[700], _pose(700)[0])
    np.testing.assert_array_equal(Cs[700], _pose(700)[1])


def test_what_the_store_hands_out_cannot_be_written_into_it():
    kfs = KeyframeStore()
    kfs.add(0.0)
    kfs.record_online(*_pose(1))
    for view in (kfs.t, kfs.online_T(0), kfs.online_cov(0)):
        with pytest.raises(ValueError):
            view[0] = 7.0
    kfs.freeze(0, *_pose(2))
    with pytest.raises(ValueError):
        kfs.frozen(0)[0][0, 0] = 7.0
    np.testing.assert_array_equal(kfs.online_T(0), _pose(1)[0])


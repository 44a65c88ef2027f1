"""Runner and relocalizer on a seeded synthetic traverse with the dead-reckoning back-end."""

from __future__ import annotations

import gc

import numpy as np
import pytest
from _synth_stream import NearestNeighbourMatcher, make_stream
from hypothesis import given, settings
from hypothesis import strategies as st

from fgslam import metrics as M
from fgslam.backends import DeadReckoning, DeadReckoningConfig, make_backend
from fgslam.fix_sources import FedFixes, OnlineFixes, ReplayedFixes
from fgslam.inputs import truth_of
from fgslam.relocalizer import (
    Relocalizer,
    RelocalizerConfig,
    RelocalizerError,
    fix_from_similarity,
    select_local_map,
)
from fgslam.runner import RunnerError, run_backend
from reloc.backend import Backend, LandmarkMap, PoseEstimate
from reloc.covariance import distance_correlation_scale


@pytest.fixture(scope="module")
def stream():
    return make_stream(seed=3, duration_s=60.0)


def _pose(x, y, yaw, t=10.0, sigma=0.1):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = x, y
    return PoseEstimate(t, T, np.eye(6) * sigma**2)


def test_dead_reckoning_is_a_backend_and_drifts(stream):
    dr = DeadReckoning(stream.initial)
    assert isinstance(dr, Backend)
    res = run_backend(dr, stream.measurements)
    gt = truth_of(stream)
    ate = M.ate(res.final, gt)
    # 5 % slip over ~14 m plus gyro bias: clearly drifting, but not absurd
    assert 0.2 < ate.max < 3.0
    assert len(res.online) == pytest.approx(res.duration_s * 10, abs=2)  # 10 Hz records
    assert res.online.cov.shape == (len(res.online), 6, 6)
    assert len(res.landmarks["rocks"]) > 30 and res.attempts == [] and res.outcomes == []


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-8, 8), st.integers(-8, 8), st.sampled_from([0.0, 0.15, 0.3, 0.6])), min_size=1,
                max_size=60), st.integers(0, 2**32 - 1))
def test_the_dead_reckoning_map_finds_the_nearest_landmark_as_a_scan_of_all(cells, seed):
    """The grid's nearest landmark within the gate is the scan's (the lowest index among equally
    near ones; points on cell borders and at exactly the gate), also after landmarks moved and
    after a fix moved the whole map."""
    from fgslam.backends.dead_reckoning import _PointMap

    gate = 0.6
    rng = np.random.default_rng(seed)
    lm = _PointMap(gate)
    pts = np.array([(gate * i + f, gate * j - f, 0.0) for i, j, f in cells])
    for p in pts:
        lm.add(p, np.eye(3), np.eye(3), 1.0)

    def check(queries):
        for q in queries:
            d = np.linalg.norm(lm.xyz[:, :2] - q[:2], axis=1)
            j = int(np.argmin(d))
            assert lm.nearest(q) == ((j, float(d[j])) if d[j] < gate else (-1, np.inf))

    queries = np.concatenate([pts + rng.choice([-gate, -0.3, 0.0, 0.3, gate], size=pts.shape) * [1, 1, 0],
                              rng.uniform(-6, 6, size=(20, 3))])
    check(queries)
    for i in rng.integers(0, len(pts), size=5):  # a fused sighting moved it
        lm.xyz[i] += rng.normal(scale=0.4, size=3)
        lm.moved(int(i))
    check(queries)
    c, s = np.cos(0.7), np.sin(0.7)
    lm.transform(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), np.array([1.3, -0.2, 0.1]))
    check(queries)
    assert len(lm.xyz) == len(pts)


def test_fix_from_similarity_undoes_a_known_map_error():
    # truth pose (5, 2, 0.3); the estimate (and its map) is off by a rigid transform D^-1;
    # a matcher returning D must give back the true pose exactly.
    a, tr = 0.1, np.array([0.7, -0.4])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    true_xy, true_yaw = np.array([5.0, 2.0]), 0.3
    est_xy = R.T @ (true_xy - tr)
    est = _pose(*est_xy, true_yaw - a)
    inliers = np.random.default_rng(0).uniform(-5, 5, (12, 2)) + est_xy
    cfg = RelocalizerConfig()
    fix = fix_from_similarity(est, a, tr, 1.0, inliers, rmse_m=0.05, cfg=cfg, t_recv=12.0)
    assert fix.t_meas == 10.0 and fix.t_recv == 12.0
    assert np.allclose([fix.x_m, fix.y_m], true_xy) and fix.yaw_rad == pytest.approx(true_yaw)
    assert np.all(np.linalg.eigvalsh(fix.cov_xyyaw) > 0)
    # more inliers, tighter fix; farther from the inlier centroid, looser position
    more = fix_from_similarity(est, a, tr, 1.0, np.vstack([inliers, inliers + 0.01]), 0.05, cfg, 12.0)
    assert np.trace(more.cov_xyyaw[:2, :2]) < np.trace(fix.cov_xyyaw[:2, :2])
    far = fix_from_similarity(est, a, tr, 1.0, inliers + [30.0, 0.0], 0.05, cfg, 12.0)
    assert np.trace(far.cov_xyyaw[:2, :2]) > np.trace(fix.cov_xyyaw[:2, :2])
    with pytest.raises(RelocalizerError, match="at least 3 inliers"):
        fix_from_similarity(est, a, tr, 1.0, inliers[:2], 0.05, cfg, 12.0)


def test_relocalizer_config_is_validated():
    with pytest.raises(RelocalizerError, match="latency"):
        RelocalizerConfig(latency="sometimes")
    with pytest.raises(RelocalizerError, match="period_s"):
        RelocalizerConfig(period_s=0.0)


def test_select_local_map_keeps_seen_landmarks_near_the_rover():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [50, 0, 0]], float)
    lm = LandmarkMap(np.arange(4), xyz, np.tile(np.eye(3), (4, 1, 1)), np.ones(4), np.array([3, 1, 5, 9]), "rocks")
    idx = select_local_map(lm, np.array([0.0, 0.0]), RelocalizerConfig(min_obs=2, max_radius_m=20.0, sparse_below=0))
    assert list(idx) == [0, 2]
    # sparse ground (fewer than sparse_below near the rover): the radius grows to sparse_radius_m
    idx = select_local_map(lm, np.array([0.0, 0.0]), RelocalizerConfig(min_obs=2, max_radius_m=20.0, sparse_radius_m=60.0))
    assert list(idx) == [0, 2, 3]
    idx = select_local_map(lm, np.array([0.0, 0.0]), RelocalizerConfig(min_obs=1, max_landmarks=3))
    assert list(idx) == [0, 1, 2]


def test_the_local_map_leaves_out_what_the_catalog_cannot_hold(stream):
    """Landmarks smaller than min_size_fraction of the catalog's 1st-percentile size are not
    matched; the bound follows the catalog the relocalizer was given."""
    xyz = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float)
    lm = LandmarkMap(np.arange(4), xyz, np.tile(np.eye(3), (4, 1, 1)), np.array([0.2, 0.6, 1.0, 2.0]),
                     np.full(4, 5), "rocks")
    cfg = RelocalizerConfig(sparse_below=0)
    assert list(select_local_map(lm, np.zeros(2), cfg, min_size_m=0.5)) == [1, 2, 3]
    assert list(select_local_map(lm, np.zeros(2), cfg)) == [0, 1, 2, 3]
    cat = stream.catalog
    reloc = Relocalizer(cat, cfg, matcher=NearestNeighbourMatcher(cat.xy_m))
    assert reloc.min_size_m == pytest.approx(0.7 * np.quantile(cat.size_m[cat.size_m > 0], 0.01))
    off = Relocalizer(cat, RelocalizerConfig(min_size_fraction=0.0), matcher=NearestNeighbourMatcher(cat.xy_m))
    assert off.min_size_m == 0.0


def test_online_relocalization_bounds_the_error_and_fixes_arrive_late(stream):
    gt = truth_of(stream)
    cfg = RelocalizerConfig(period_s=4.0, delay_s=1.5)
    reloc = Relocalizer(stream.catalog, cfg, matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    be = make_backend("dr", stream.initial, {"use_fixes": True})
    res = run_backend(be, stream.measurements, OnlineFixes([reloc]))
    base = run_backend(make_backend("dr", stream.initial), stream.measurements)
    fixes = [a.fix for a in res.attempts if a.fix is not None]
    assert len(res.attempts) == pytest.approx(res.duration_s / 4.0, abs=1)
    assert len(fixes) >= 0.7 * len(res.attempts)
    assert all(f.t_recv == pytest.approx(f.t_meas + 1.5) for f in fixes)
    # every fix delivered (except those due after the end) and accepted
    assert len(res.outcomes) == sum(f.t_recv <= res.t_end for f in fixes)
    assert all(o.accepted for o in res.outcomes)
    pos_err, _ = M.fix_errors(np.array([f.xyyaw for f in fixes]), np.array([f.t_meas for f in fixes]), gt)
    assert np.median(pos_err) < 0.5
    assert M.ate(res.final, gt).rmse < 0.7 * M.ate(base.final, gt).rmse


def test_replaying_the_fix_list_reproduces_the_online_run(stream):
    cfg = RelocalizerConfig(period_s=4.0, delay_s=1.0)
    reloc = Relocalizer(stream.catalog, cfg, matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    online = run_backend(make_backend("dr", stream.initial, {"use_fixes": True}), stream.measurements, OnlineFixes([reloc]))
    fixes = [a.fix for a in online.attempts if a.fix is not None]
    replay = run_backend(make_backend("dr", stream.initial, {"use_fixes": True}), stream.measurements, ReplayedFixes(fixes))
    assert [o.fix for o in replay.outcomes] == [o.fix for o in online.outcomes]
    assert np.allclose(replay.final.T_world_base, online.final.T_world_base)


class _Odd:
    """A stamped object that is no measurement of any registered kind."""

    def __init__(self, t):
        self.t = t


def test_runner_rejects_bad_streams(stream):
    with pytest.raises(RunnerError, match="empty"):
        run_backend(DeadReckoning(stream.initial), [])
    imu_free = [m for m in stream.measurements[:200] if type(m).__name__ != "ImuSample"]
    with pytest.raises(RunnerError, match="IMU"):
        run_backend(DeadReckoning(stream.initial), imu_free)
    with pytest.raises(RunnerError, match="cannot consume _Odd at t=0.5: _Odd is not the observation of any registered"):
        run_backend(DeadReckoning(stream.initial), [*stream.measurements[:10], _Odd(0.5)])


def test_dead_reckoning_config_overrides_are_checked(stream):
    from reloc.errors import ConfigError

    with pytest.raises(ConfigError, match="no_such_key"):
        make_backend("dr", stream.initial, {"no_such_key": 1})
    assert make_backend("dr", stream.initial, {"use_fixes": True}).config == DeadReckoningConfig(use_fixes=True)


def _map_and_pose(stream):
    be = make_backend("dr", stream.initial)
    run_backend(be, stream.measurements[: len(stream.measurements) // 2])
    return be.landmark_map("rocks"), be.estimate()


def test_successive_fixes_are_deweighted_for_their_shared_error(stream):
    lmap, est = _map_and_pose(stream)
    # one map snapshot, attempted again; the correlation factor alone (no rover-relative term)
    cfg = RelocalizerConfig(correlation="window", correlation_window_s=60.0, min_landmarks=5,
                             min_new_observations=0, max_relative_sigmas=None)
    reloc = Relocalizer(stream.catalog, cfg, matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    a1 = reloc.attempt(lmap, est)
    a2 = reloc.attempt(lmap, PoseEstimate(est.t + 3.0, est.T_world_base, est.cov))
    a3 = reloc.attempt(lmap, PoseEstimate(est.t + 100.0, est.T_world_base, est.cov))
    assert a1.fix is not None and a2.fix is not None and a3.fix is not None
    assert np.allclose(a2.fix.cov_xyyaw, 2.0 * a1.fix.cov_xyyaw)  # one fix in the window before
    assert np.allclose(a3.fix.cov_xyyaw, a1.fix.cov_xyyaw)  # the window has passed


def test_fixes_on_shared_catalog_rocks_are_deweighted_whenever_they_were_made(stream):
    """correlation "rocks": the covariance grows with the earlier fixes' use of the same catalog
    rocks, however long ago; a fix on other rocks keeps its own covariance."""
    lmap, est = _map_and_pose(stream)
    reloc = Relocalizer(stream.catalog, RelocalizerConfig(min_landmarks=5, min_new_observations=0,  # one snapshot
                                                          max_relative_sigmas=None),  # the factor alone
                        matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    assert reloc.config.correlation == "rocks"
    a1 = reloc.attempt(lmap, est)
    a2 = reloc.attempt(lmap, PoseEstimate(est.t + 3.0, est.T_world_base, est.cov))
    a3 = reloc.attempt(lmap, PoseEstimate(est.t + 500.0, est.T_world_base, est.cov))
    assert a1.status == a2.status == a3.status == "fix"
    assert np.allclose(a2.fix.cov_xyyaw, 2.0 * a1.fix.cov_xyyaw)  # every rock used once before
    assert np.allclose(a3.fix.cov_xyyaw, 3.0 * a1.fix.cov_xyyaw)  # ... and twice, 500 s later
    # half of the rocks used three times before, half new: 1 + mean use
    rows = np.flatnonzero(reloc._rock_uses)  # the catalog rocks of those fixes
    fresh = Relocalizer(stream.catalog, RelocalizerConfig(min_landmarks=5, max_relative_sigmas=None),
                        matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    fresh._rock_uses[rows[: rows.size // 2]] = 3
    assert fresh._correlation_scale(0.0, rows) == pytest.approx(1.0 + 3.0 * (rows.size // 2) / rows.size)
    with pytest.raises(RelocalizerError, match="correlation"):
        RelocalizerConfig(correlation="time")


def test_distance_correlation_scale_is_the_variance_of_the_mean_of_gauss_markov_fixes():
    """Fixes d metres apart whose errors correlate as exp(-d / L), fused as independent with
    their covariance times the scale, give the variance the mean of such a sequence has."""
    rng = np.random.default_rng(5)
    L, d, n, runs = 15.0, 1.2, 1500, 3000
    rho = np.exp(-d / L)
    e = np.empty((runs, n))
    e[:, 0] = rng.standard_normal(runs)
    w = np.sqrt(1.0 - rho**2) * rng.standard_normal((runs, n))
    for k in range(1, n):
        e[:, k] = rho * e[:, k - 1] + w[:, k]
    fused_var = distance_correlation_scale(d, L) / n  # n independent fixes of variance 1 x scale
    assert np.var(e.mean(axis=1)) == pytest.approx(fused_var, rel=0.08)
    assert distance_correlation_scale(10.0 * L, L) == pytest.approx(1.0, abs=1e-3)  # far apart: independent
    assert distance_correlation_scale(0.0, L) == pytest.approx(distance_correlation_scale(0.01 * L, L))  # floored


def test_fixes_are_deweighted_by_the_path_since_the_previous_one(stream):
    """correlation "distance": a fix on the same place again adds almost nothing (the scale at the
    floor), one 20 correlation lengths further on counts as independent."""
    lmap, est = _map_and_pose(stream)
    cfg = RelocalizerConfig(correlation="distance", correlation_length_m=2.0, min_landmarks=5, min_new_observations=0,
                            max_relative_sigmas=None)  # the correlation factor alone
    reloc = Relocalizer(stream.catalog, cfg, matcher=NearestNeighbourMatcher(stream.catalog.xy_m))
    a1 = reloc.attempt(lmap, est)
    a2 = reloc.attempt(lmap, PoseEstimate(est.t + 3.0, est.T_world_base, est.cov))
    T = est.T_world_base.copy()
    T[0, 3] += 20.0  # attempts on the way: the path is summed between attempts
    reloc.attempt(LandmarkMap.empty("rocks"), PoseEstimate(est.t + 50.0, T, est.cov))
    a3 = reloc.attempt(lmap, PoseEstimate(est.t + 100.0, est.T_world_base, est.cov))
    assert a1.status == a2.status == a3.status == "fix"
    assert np.allclose(a2.fix.cov_xyyaw, distance_correlation_scale(0.0, 2.0) * a1.fix.cov_xyyaw)
    assert np.allclose(a3.fix.cov_xyyaw, a1.fix.cov_xyyaw, rtol=1e-3)  # 40 m of path: 20 lengths
    # each fix says what it is, so a consumer can weigh it by its own model (GlobalFix.recorrelated)
    assert a2.fix.source == "rocks" and a2.fix.correlation_scale == pytest.approx(distance_correlation_scale(0.0, 2.0))
    assert np.allclose(a2.fix.recorrelated(1.0).cov_xyyaw, a1.fix.cov_xyyaw)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(RelocalizerError, match="correlation_length_m"):
            RelocalizerConfig(correlation="distance", correlation_length_m=bad)


def test_nearby_attempts_share_one_catalog_crop_and_its_fix(stream):
    """Crops are cut on a grid: attempts a few decimetres apart reuse one crop (and its index),
    and the cached crop gives the fix a fresh relocalizer gives."""
    lmap, est = _map_and_pose(stream)
    cfg = RelocalizerConfig(min_landmarks=5, correlation="none", min_new_observations=0)  # one map snapshot
    reloc = Relocalizer(stream.catalog, cfg)
    first = reloc.attempt(lmap, est)
    T = est.T_world_base.copy()
    T[:2, 3] += 0.05  # the rover has moved a little; its map has not
    again = reloc.attempt(lmap, PoseEstimate(est.t + 3.0, T, est.cov))
    assert first.status == again.status == "fix"
    assert reloc.n_crops_built == 1
    fresh = Relocalizer(stream.catalog, cfg).attempt(lmap, PoseEstimate(est.t + 3.0, T, est.cov))
    assert np.allclose(fresh.fix.xyyaw, again.fix.xyyaw) and np.allclose(fresh.fix.cov_xyyaw, again.fix.cov_xyyaw)
    with pytest.raises(RelocalizerError, match="crop_snap_m"):
        RelocalizerConfig(crop_snap_m=0.0)


def test_select_local_map_prefers_the_largest_rocks_within_the_radius():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [8, 0, 0], [50, 0, 0]], float)
    size = np.array([0.1, 0.5, 0.1, 0.4, 1.0])
    lm = LandmarkMap(np.arange(5), xyz, np.tile(np.eye(3), (5, 1, 1)), size, np.full(5, 3), "rocks")
    rover = np.array([0.0, 0.0])
    assert list(select_local_map(lm, rover, RelocalizerConfig(max_landmarks=3, max_radius_m=20.0, sparse_below=0))) == [0, 1, 3]
    near = RelocalizerConfig(max_landmarks=3, max_radius_m=20.0, select="nearest", sparse_below=0)
    assert list(select_local_map(lm, rover, near)) == [0, 1, 2]
    with pytest.raises(RelocalizerError, match="select"):
        RelocalizerConfig(select="biggest")


def test_similarity_covariance_is_propagated_to_the_fix():
    est = _pose(4.0, -3.0, 0.5)
    a, tr, s = 0.2, np.array([1.0, 2.0]), 1.01
    C4 = np.diag([0.01, 0.02, 1e-4, 1e-5])
    cfg = RelocalizerConfig(inflation=1.0, sigma_floor_m=0.0, sigma_yaw_floor_rad=0.0)
    inl = np.random.default_rng(1).normal(size=(10, 2))
    fix = fix_from_similarity(est, a, tr, s, inl, 0.05, cfg, 11.0, similarity_cov=C4)

    def f(p):  # (tx, ty, theta, scale) -> (x, y, yaw)
        c, si = np.cos(p[2]), np.sin(p[2])
        xy = p[3] * np.array([[c, -si], [si, c]]) @ est.position_m[:2] + p[:2]
        return np.array([xy[0], xy[1], est.yaw_rad + p[2]])

    p0 = np.array([tr[0], tr[1], a, s])
    J = np.column_stack([(f(p0 + h) - f(p0 - h)) / 2e-6 for h in np.eye(4) * 1e-6])
    assert np.allclose(fix.cov_xyyaw, J @ C4 @ J.T, rtol=1e-5, atol=1e-12)
    assert np.allclose(fix.xyyaw, f(p0))


def test_cropped_catalog_gives_the_whole_catalog_fix(stream):
    """With a prior, matching against the catalog crop that can hold the map finds the same fix,
    and its matched pairs index the full catalog."""
    be = make_backend("dr", stream.initial)
    run_backend(be, stream.measurements[: len(stream.measurements) // 2])
    lmap, est = be.landmark_map("rocks"), be.estimate()
    out = {}
    for crop in (True, False):
        reloc = Relocalizer(stream.catalog, RelocalizerConfig(min_landmarks=5, crop_catalog=crop))
        out[crop] = reloc.attempt(lmap, est)
    assert out[True].status == out[False].status == "fix"
    assert np.allclose(out[True].fix.xyyaw, out[False].fix.xyyaw, atol=0.05)
    cat = {tuple(p) for p in np.round(stream.catalog.xy_m, 9)}
    assert all(tuple(p) in cat for p in np.round(out[True].world_xy, 9))


def test_a_coarse_crop_hash_for_a_wide_matcher_sigma_gives_the_same_fix(stream, monkeypatch):
    """At a wide matcher sigma (0.4 m here, 0.5 m on the kilometre worlds) the crops are hashed with
    bins of half the side tolerance instead of 0.08 m (a query walks a few dozen bins, not
    hundreds): the same candidates reach the exact side test, and the attempt gives the fix the
    fine hash gives."""
    be = make_backend("dr", stream.initial)
    run_backend(be, stream.measurements[: len(stream.measurements) // 2])
    lmap, est = be.landmark_map("rocks"), be.estimate()
    sigma = 0.4
    cfg = RelocalizerConfig(min_landmarks=5, min_new_observations=0, matcher={"sigma_m": sigma})
    coarse = Relocalizer(stream.catalog, cfg)
    assert coarse._hash_bin_m() == pytest.approx(0.5 * np.sqrt(2.0) * sigma)
    a = coarse.attempt(lmap, est)
    monkeypatch.setattr(Relocalizer, "_hash_bin_m", lambda self: 0.08)
    b = Relocalizer(stream.catalog, cfg).attempt(lmap, est)
    assert a.status == b.status == "fix"
    assert np.allclose(a.fix.xyyaw, b.fix.xyyaw) and np.allclose(a.fix.cov_xyyaw, b.fix.cov_xyyaw)
    assert a.fix.catalog_rows == b.fix.catalog_rows
    assert Relocalizer(stream.catalog, RelocalizerConfig())._hash_bin_m() == pytest.approx(0.08)  # a yard's sigma


def test_runner_config_is_checked():
    from fgslam.runner import RunnerConfig

    with pytest.raises(RunnerError, match="blas_threads"):
        RunnerConfig(blas_threads=-1)
    with pytest.raises(RunnerError, match="record_rate_hz"):
        RunnerConfig(record_rate_hz=0.0)


def test_attempts_wait_until_the_rover_has_moved_or_turned(stream):
    nn = NearestNeighbourMatcher(stream.catalog.xy_m)
    reloc = Relocalizer(stream.catalog, RelocalizerConfig(min_travel_m=0.05, min_turn_deg=3.0), matcher=nn)
    assert reloc.wants(_pose(0.0, 0.0, 0.0))  # the first attempt always
    reloc.attempt(LandmarkMap.empty("rocks"), _pose(0.0, 0.0, 0.0))
    assert not reloc.wants(_pose(0.03, 0.0, 0.02))  # standing (almost) still
    assert reloc.wants(_pose(0.04, 0.04, 0.0))  # moved 5.7 cm
    assert reloc.wants(_pose(0.0, 0.0, np.radians(4.0)))  # turned 4 deg on the spot
    never = Relocalizer(stream.catalog, RelocalizerConfig(min_travel_m=0.0, min_turn_deg=0.0), matcher=nn)
    never.attempt(LandmarkMap.empty("rocks"), _pose(0.0, 0.0, 0.0))
    assert never.wants(_pose(0.0, 0.0, 0.0))


class _Recorder:
    """Wraps a back-end: records the newest input time whenever ``expect_fix`` is called."""

    def __init__(self, inner):
        self.inner, self.name, self.calls, self.t_in = inner, inner.name, [], -np.inf

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def predict(self, step):
        self.t_in = step.t1
        return self.inner.predict(step)

    def update_landmarks(self, obs):
        self.t_in = obs.t
        return self.inner.observe(obs)

    def expect_fix(self, t_meas):
        self.calls.append((t_meas, self.t_in))
        return self.inner.expect_fix(t_meas)


class _ListFeed:
    """A fix feed over a known list (the protocol of fgslam.runner.FixFeed, never blocking)."""

    def __init__(self, fixes):
        self._left = sorted(fixes, key=lambda f: f.t_recv)

    def until(self, t):
        out = [f for f in self._left if f.t_recv <= t]
        self._left = self._left[len(out):]
        return out

    def rest(self):
        out, self._left = self._left, []
        return out


def test_a_rolling_back_backend_hears_of_each_fix_before_the_stream_passes_it(stream):
    from reloc.measurements import GlobalFix

    gt = truth_of(stream)
    fixes = []
    for t in (12.3, 25.0, 41.7):
        T = gt.T_world_base[np.searchsorted(gt.t, t)]
        fixes.append(GlobalFix(t, t + 2.0, T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])), np.eye(3) * 0.01))
    runs = {}
    for mode in ("list", "feed"):
        be = _Recorder(make_backend("ekf", stream.initial))
        source = ReplayedFixes(fixes) if mode == "list" else FedFixes(_ListFeed(fixes))
        res = run_backend(be, stream.measurements, source)
        assert [c[0] for c in be.calls] == [f.t_meas for f in fixes]
        assert all(t_in <= t_meas for t_meas, t_in in be.calls)  # told before any later input
        assert all(o.accepted for o in res.outcomes)
        runs[mode] = (res, be.inner.stats().extra["n_replayed_entries"])
    # same fixes, same result, and only the inputs after each t_meas replayed
    np.testing.assert_allclose(runs["list"][0].final.T_world_base, runs["feed"][0].final.T_world_base, atol=1e-12)
    assert runs["list"][1] == runs["feed"][1]


def test_tracking_verifies_the_estimate_and_searches_when_it_is_off(stream):
    """With ``track`` the estimate's own pose is verified first: the same fix as the search where
    the estimate is good; an estimate 1.5 m and 8 deg off is not tracked but still found."""
    import dataclasses

    be = make_backend("dr", stream.initial)
    run_backend(be, stream.measurements[: len(stream.measurements) // 2])
    lmap, est = be.landmark_map("rocks"), be.estimate()
    cfg = RelocalizerConfig(min_landmarks=5)
    out = {tr: Relocalizer(stream.catalog, dataclasses.replace(cfg, track=tr)).attempt(lmap, est) for tr in (True, False)}
    assert out[True].status == out[False].status == "fix"
    assert out[True].tracked and not out[False].tracked
    assert np.allclose(out[True].fix.xyyaw, out[False].fix.xyyaw, atol=0.05)
    # move the snapshot (map and estimate together) by a rigid 2D error the search must undo
    yaw = np.radians(8.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    off = np.array([1.5, 0.0, 0.0])
    # (the map placed from the drifted poses: their 1 m sigma is in its covariance too)
    moved = LandmarkMap(lmap.ids, lmap.xyz_world_m @ R.T + off, lmap.cov_world_m2 + np.eye(3), lmap.size_m,
                        lmap.n_obs, "rocks")
    T = est.T_world_base.copy()
    T[:3, :3], T[:3, 3] = R @ T[:3, :3], R @ T[:3, 3] + off
    drifted = PoseEstimate(est.t, T, np.eye(6) * 1.0)
    att = Relocalizer(stream.catalog, dataclasses.replace(cfg, track=True)).attempt(moved, drifted)
    assert att.status == "fix" and not att.tracked
    assert np.allclose(att.fix.xyyaw[:2], out[False].fix.xyyaw[:2], atol=0.1)
    assert abs(M.wrap_angle(att.fix.xyyaw[2] - out[False].fix.xyyaw[2])) < np.radians(1.0)


def test_rover_weighted_fit_follows_the_map_near_the_rover():
    """A map whose far half is displaced 0.3 m (drift built up away from the rover): the
    rover-weighted fit recovers the near half's transform, the plain fit is pulled half way;
    with weights all 1 the covariance is the plain one, and it grows when the rocks are far."""
    from fgslam.relocalizer import rover_weighted_fit
    from reloc.match_result import similarity_covariance
    from reloc.procrustes import Similarity2D, umeyama_2d

    rng = np.random.default_rng(5)
    world = rng.uniform(-25, 25, (120, 2))
    rover = np.array([-20.0, 0.0])
    far = np.linalg.norm(world - rover, axis=1) > 25.0
    local = world + rng.normal(0, 0.03, world.shape)
    local[far] += [0.3, 0.0]  # the far part of the local map is off; near the rover it is right
    theta, t, s, rmse, cov = rover_weighted_fit(local, world, rover, 8.0, 0.025)
    plain = umeyama_2d(local, world, with_scale=False)
    at_rover = Similarity2D(theta, t, s).apply(rover[None])[0]
    w = 1.0 / (1.0 + np.sum((local - rover) ** 2, axis=1) / 8.0**2)
    r_plain = np.sum((plain.apply(local) - world) ** 2, axis=1)
    assert rmse <= np.sqrt(np.sum(w * r_plain) / np.sum(w))  # it minimises the weighted residuals
    err_w, err_plain = np.linalg.norm(at_rover - rover), np.linalg.norm(plain.apply(rover[None])[0] - rover)
    assert err_w < 0.08 and err_w < 0.5 * err_plain, (err_w, err_plain)
    assert s == 1.0 and cov.shape == (4, 4) and np.all(np.linalg.eigvalsh(cov[:3, :3]) > 0)
    ones = similarity_covariance(plain, local, world, with_scale=False, weights=np.ones(len(world)))
    assert np.allclose(ones, similarity_covariance(plain, local, world, with_scale=False))
    # the same rocks seen from a rover 40 m further away: the fix is less certain
    cov_far = rover_weighted_fit(local, world, rover - [40.0, 0.0], 8.0, 0.025)[4]
    assert cov_far[0, 0] > 2 * cov[0, 0]
    with pytest.raises(RelocalizerError, match="fit_radius_m"):
        RelocalizerConfig(fit_radius_m=0.0)


def test_a_front_end_computed_once_gives_every_pass_its_own_run(stream):
    """The slip- and gyro-corrected steps of an in-memory stream, computed once for a comparison's
    passes (fgslam.front_end.SharedSteps), give each back-end the very run its own front-end gives."""
    from dataclasses import replace

    from fgslam.runner import RunnerConfig, shared_steps

    cfg = RunnerConfig()
    steps = shared_steps(stream.measurements, cfg)
    assert steps.stats["slip"]["n_checks"] > 10 and steps.stats["gyro"]["n_checks"] > 0
    for name in ("dr", "ekf", "isam2"):
        own = run_backend(make_backend(name, stream.initial), stream.measurements, config=cfg)
        shared = run_backend(make_backend(name, stream.initial), stream.measurements, config=cfg, steps=steps)
        assert np.array_equal(own.final.T_world_base, shared.final.T_world_base), name
        assert np.array_equal(own.online.cov, shared.online.cov), name
        assert (own.extra["slip"], own.extra["gyro"]) == (shared.extra["slip"], shared.extra["gyro"]), name
    # steps of another list, or of another front-end config, are not used: the pass computes its own
    assert steps.matches(stream.measurements, replace(cfg, record_rate_hz=1.0))
    assert not steps.matches(list(stream.measurements), cfg)
    assert not steps.matches(stream.measurements, replace(cfg, speed_source="wheel"))
    assert not steps.matches(stream.measurements, replace(cfg, slip=replace(cfg.slip, enabled=False)))
    assert not steps.R0.flags.writeable and not steps.scalars.flags.writeable  # shared: never written


class _FreezeProbe(DeadReckoning):
    """Dead reckoning that records the collector's frozen count at each frame."""

    def __init__(self, initial):
        super().__init__(initial)
        self.frozen: list[int] = []

    def observe(self, obs):
        self.frozen.append(gc.get_freeze_count())
        return super().observe(obs)


def test_the_run_keeps_its_starting_objects_out_of_the_collectors_passes(stream):
    from fgslam.runner import RunnerConfig, frozen_heap

    before = gc.get_freeze_count()
    probe = _FreezeProbe(stream.initial)
    res = run_backend(probe, stream.measurements)
    # the stream (thousands of measurement objects) is frozen while the pass runs, and let go after
    assert min(probe.frozen) > len(stream.measurements) and gc.get_freeze_count() == before
    off = _FreezeProbe(stream.initial)
    res_off = run_backend(off, stream.measurements, config=RunnerConfig(freeze_heap=False))
    assert max(off.frozen) == before
    np.testing.assert_array_equal(res.final.T_world_base, res_off.final.T_world_base)  # same estimate
    with frozen_heap():  # nested (a thread's pass inside another's): the outer one unfreezes
        n = gc.get_freeze_count()
        with frozen_heap():
            assert gc.get_freeze_count() == n
        assert gc.get_freeze_count() == n > 0
    assert gc.get_freeze_count() == before
    gc.freeze()  # a process that froze its own objects keeps its freeze after a pass
    try:
        mine = gc.get_freeze_count()
        run_backend(_FreezeProbe(stream.initial), stream.measurements)
        assert gc.get_freeze_count() > 0.99 * mine > 0  # (less what died by reference count)
    finally:
        gc.unfreeze()


def test_the_run_hands_the_free_heap_back_on_its_schedule(stream):
    """RunnerConfig.trim_heap_every_s: a trim every so many seconds of stream, none with 0, and
    the estimate the same either way."""
    from fgslam.runner import RunnerConfig

    on = run_backend(DeadReckoning(stream.initial), stream.measurements, config=RunnerConfig(trim_heap_every_s=10.0))
    off = run_backend(DeadReckoning(stream.initial), stream.measurements, config=RunnerConfig(trim_heap_every_s=0.0))
    span = on.t_end - on.t_start
    assert int(span // 10.0) - 1 <= on.extra["heap_trim"]["n"] <= int(span // 10.0)
    assert off.extra["heap_trim"] == {"n": 0, "cpu_s": 0.0}
    np.testing.assert_array_equal(on.final.T_world_base, off.final.T_world_base)


def test_release_free_heap_returns_freed_blocks_in_the_middle_of_the_heap():
    """Blocks freed between live ones stay resident under glibc until trimmed; the trim gives
    them back (where the C library has malloc_trim)."""
    from fgslam.runner import _malloc_trim, release_free_heap, resident_memory_mb

    if _malloc_trim() is None:
        pytest.skip("no malloc_trim in this C library")
    blocks = [np.ones(100_000 // 8) for _ in range(1500)]  # 150 MB of heap blocks (below mmap's threshold)
    keep = blocks[::50]  # one live block in fifty: the heap's top is never free
    del blocks
    before = resident_memory_mb()["rss_mb"]
    assert release_free_heap()
    after = resident_memory_mb()["rss_mb"]
    assert before - after > 50.0, (before, after)
    assert all(b[0] == 1.0 for b in keep)

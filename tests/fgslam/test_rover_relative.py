"""A fix is the rover moved with its map, so it is only as good as the rover's place relative to
the landmarks matched. After a blind spell the map's old part is right in the world but the
rover has drifted from it; the part mapped since carries the rover's drift. Matching the old
part repeats the drifted pose; the relocalizer leaves out landmarks the rover has drifted from
(more than ``max_relative_sigmas`` matcher sigmas) and adds the inliers' relative covariance to
the fix's."""

from __future__ import annotations

import dataclasses

import numpy as np
from _synth_stream import make_stream

from fgslam.backends.dead_reckoning import DeadReckoning
from fgslam.match_to_fix import rover_relative_cov_xy
from fgslam.relocalizer import Relocalizer
from fgslam.relocalizer_config import RelocalizerConfig
from fgslam.runner import run_backend
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.measurements import RockCatalog

DRIFT = np.array([0.45, -0.3])  # what the rover drifted while blind (m)
ROVER = np.array([30.0, 20.0])  # where it truly is


def _world(seed: int = 3):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 60.0, (900, 2))
    size = rng.uniform(0.3, 1.2, len(xy))
    return xy, size


def _snapshot(n_new: int, rel_sigma_old: float = 0.3):
    """The rover's estimate (drifted by DRIFT, its sigma grown to ``rel_sigma_old`` while blind)
    and its map: the rocks behind it (seen before the blind spell, in the right place, their
    covariance the rover's of then) and ``n_new`` rocks ahead seen since (moved by DRIFT, their
    covariance the rover's now)."""
    xy, size = _world()
    d = xy - ROVER
    behind = np.flatnonzero((d[:, 0] < -1.0) & (np.linalg.norm(d, axis=1) < 14.0))
    ahead = np.flatnonzero((d[:, 0] > 1.0) & (np.linalg.norm(d, axis=1) < 9.0))[:n_new]
    rng = np.random.default_rng(11)
    sig_then = 0.03
    T = np.eye(4)
    T[:2, 3] = ROVER + DRIFT
    cov = np.diag([rel_sigma_old**2, rel_sigma_old**2, 0.01, 1e-4, 1e-4, 1e-4])
    est = PoseEstimate(180.0, T, cov)
    pos = np.vstack([xy[behind], xy[ahead] + DRIFT]) + rng.normal(0.0, 0.02, (len(behind) + len(ahead), 2))
    covs = np.concatenate([np.repeat((np.eye(3) * (sig_then**2 + 0.02**2))[None], len(behind), 0),
                           np.repeat((np.eye(3) * 0.02**2 + np.diag([rel_sigma_old**2] * 2 + [0.0]))[None],
                                     len(ahead), 0)])
    n = len(pos)
    lmap = LandmarkMap(np.arange(n), np.column_stack([pos, np.zeros(n)]), covs,
                       np.concatenate([size[behind], size[ahead]]), np.full(n, 5), "rocks")
    catalog = RockCatalog(xy, size, np.ones(len(xy)))
    return est, lmap, catalog, len(behind)


def test_relative_covariance_is_the_rovers_growth_since_the_landmark_was_seen():
    rover = np.diag([0.09, 0.04])
    in_view = rover + np.eye(2) * 0.001  # its covariance holds the rover's now
    old = np.eye(2) * 0.0009  # seen when the rover was at 3 cm
    rel = rover_relative_cov_xy(np.stack([in_view, old]), rover)
    assert np.allclose(rel[0], 0.0, atol=1e-12)
    assert np.allclose(rel[1], rover - old)
    # partly grown: only the positive part counts, and it stays symmetric positive semidefinite
    rel = rover_relative_cov_xy(np.diag([0.2, 0.01])[None], rover)[0]
    assert np.allclose(rel, np.diag([0.0, 0.03]))


def test_old_landmarks_are_left_out_and_the_fix_finds_the_rover_not_its_drift():
    est, lmap, catalog, n_old = _snapshot(n_new=14)
    assert n_old > 14  # the old part outnumbers the new
    base = RelocalizerConfig(min_landmarks=6, fit_radius_m=None)
    off = Relocalizer(catalog, dataclasses.replace(base, max_relative_sigmas=None)).attempt(lmap, est)
    on = Relocalizer(catalog, base).attempt(lmap, est)
    assert off.status == on.status == "fix"
    err_off = np.linalg.norm(off.fix.xyyaw[:2] - ROVER)
    err_on = np.linalg.norm(on.fix.xyyaw[:2] - ROVER)
    # matched on the old part, the fix repeats the drifted pose; on the new part it finds the rover
    assert err_off > 0.8 * np.linalg.norm(DRIFT)
    assert err_on < 0.1
    assert on.fix.n_inliers <= 14
    # the inliers were seen since the blind spell: nothing relative to add, the fix claims cm
    assert np.sqrt(np.trace(on.fix.cov_xyyaw[:2, :2]) / 2) < 0.1


def test_only_old_landmarks_give_no_confident_fix():
    """With nothing seen since the blind spell no landmark ties the rover to the map: no fix
    (rather than a drifted one claiming centimetres)."""
    est, lmap, catalog, _ = _snapshot(n_new=0)
    att = Relocalizer(catalog, RelocalizerConfig(min_landmarks=6)).attempt(lmap, est)
    assert att.status == "too few landmarks"
    # a looser rule lets them in, and the fix then says how far the rover may have drifted
    loose = Relocalizer(catalog, RelocalizerConfig(min_landmarks=6, max_relative_sigmas=10.0)).attempt(lmap, est)
    assert loose.status == "fix"
    err = np.linalg.norm(loose.fix.xyyaw[:2] - ROVER)
    sigma = np.sqrt(np.linalg.eigvalsh(loose.fix.cov_xyyaw[:2, :2])[-1])
    assert err > 0.4 and sigma > 0.25  # honest: the drift is inside ~2 sigma
    assert err < 2.5 * sigma


def test_a_lost_estimate_matches_its_whole_map():
    """Lost (sigma above lost_sigma_m) every landmark is relative to the unknown start alike."""
    est, lmap, catalog, _ = _snapshot(n_new=0, rel_sigma_old=8.0)
    att = Relocalizer(catalog, RelocalizerConfig(min_landmarks=6)).attempt(lmap, est)
    assert att.n_landmarks > 6 and att.status != "too few landmarks"


def test_dead_reckoning_map_holds_the_rovers_covariance_when_seen():
    """The dead-reckoning back-end reports where its landmarks are in the world (the rover's
    uncertainty when last seen included), as the map contract says, so that the relative rule
    keeps the landmarks in view."""
    stream = make_stream(seed=3, duration_s=60.0)
    be = DeadReckoning(stream.initial)
    run_backend(be, stream.measurements[: len(stream.measurements) // 3])
    lmap, est = be.landmark_map("rocks"), be.estimate()
    assert len(lmap) > 10
    rel = rover_relative_cov_xy(lmap.cov_world_m2[:, :2, :2], est.cov[:2, :2])
    # the rocks seen last are tied to the rover; the first ones it has drifted from since
    grown = np.trace(rel, axis1=1, axis2=2) / np.trace(est.cov[:2, :2])
    assert grown.min() < 0.05
    assert grown.max() > 0.5


def test_the_relative_term_is_not_multiplied_by_the_catalog_correlation():
    """A second fix on the same catalog rocks has its catalog part doubled (correlation "rocks"),
    but the rover's drift from its map is the same drift, added once."""
    est, lmap, catalog, _ = _snapshot(n_new=0)
    cfg = RelocalizerConfig(min_landmarks=6, min_new_observations=0)
    plain = Relocalizer(catalog, dataclasses.replace(cfg, max_relative_sigmas=None))
    rel = Relocalizer(catalog, dataclasses.replace(cfg, max_relative_sigmas=10.0))
    later = PoseEstimate(est.t + 2.0, est.T_world_base, est.cov)
    p1, p2 = plain.attempt(lmap, est).fix, plain.attempt(lmap, later).fix
    r1, r2 = rel.attempt(lmap, est).fix, rel.attempt(lmap, later).fix
    assert np.allclose(p2.cov_xyyaw, 2.0 * p1.cov_xyyaw)
    added = r1.cov_xyyaw - p1.cov_xyyaw
    assert np.trace(added[:2, :2]) > 0.1  # ~(0.3 m)^2 per axis of drift
    assert np.allclose(r2.cov_xyyaw - p2.cov_xyyaw, added)

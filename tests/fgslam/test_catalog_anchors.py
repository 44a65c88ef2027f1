"""Catalog anchors: a crater identified with its catalog entry puts the entry on the crater's own
variable, once, in both SLAM back-ends (its error counted once however many fixes would repeat
it); the relocalizer names the landmarks and entries, leaves anchored craters out of later
identifications, and a landmark the back-end no longer holds gets the fix as a pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _synth_stream import CraterField, make_stream

from fgslam.backends.registry import make_backend
from fgslam.crater_relocalizer import CraterRelocalizer
from fgslam.fault_fixes import WrongFixes
from fgslam.inputs import truth_of
from fgslam.relocalizer_config import RelocalizerError
from fgslam.runner import run_backend
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.errors import MeasurementError
from reloc.measurements import CatalogAnchor, FixHeight, GlobalFix, RockCatalog
from sim.faults import WrongFixesConfig

SEED, FIELD_M = 21, 40.0
SIGMA_ENTRY_M = 0.05


@pytest.fixture(scope="module")
def stream():
    return make_stream(seed=SEED, duration_s=40.0, craters=True, field_m=FIELD_M)


def _offset_start(stream, dx: float = 0.6, sigma_z_m: float = 0.01) -> PoseEstimate:
    T = stream.initial.T_world_base.copy()
    T[0, 3] += dx
    return PoseEstimate(stream.initial.t, T, np.diag([0.4**2, 0.4**2, sigma_z_m**2, 1e-6, 1e-6, 1e-4]))


def _err(be, gt) -> float:
    e = be.estimate()
    k = min(int(np.searchsorted(gt.t, e.t)), len(gt.t) - 1)
    return float(np.linalg.norm(e.position_m[:2] - gt.positions_m[k, :2]))


def _anchor_fix(be, truth_xy: np.ndarray, lid: int | None = None, row: int = 0) -> tuple[GlobalFix, int]:
    """A single fix on the best-observed crater of ``be``'s map, its entry the crater's true
    position (to SIGMA_ENTRY_M): the pose form as the relocalizer makes it, and the anchor."""
    lm = be.landmark_map("craters")
    k = int(np.argmax(lm.n_obs)) if lid is None else int(np.flatnonzero(lm.ids == lid)[0])
    j = int(np.argmin(np.linalg.norm(truth_xy - lm.xyz_world_m[k, :2], axis=1)))
    entry = truth_xy[j]
    est = be.estimate()
    xy = est.position_m[:2] + entry - lm.xyz_world_m[k, :2]
    cov = np.diag([0.2**2, 0.2**2, 0.05**2])
    anchor = CatalogAnchor("craters", int(lm.ids[k]), row, entry, np.eye(2) * SIGMA_ENTRY_M**2)
    return GlobalFix(est.t, est.t + 1.0, xy[0], xy[1], est.yaw_rad, cov, n_inliers=1, source="craters",
                     catalog_rows=(row,), anchors=(anchor,)), int(lm.ids[k])


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_an_anchor_puts_the_entry_on_the_crater_once(stream, name):
    """Started 0.6 m off, the crater map is 0.6 m off with it; the entry on one crater moves that
    crater onto it (within 3 sigma) and the rover with it; the map reports the anchored entry; the
    same entry again is refused, and a fix naming a landmark the back-end does not hold is taken
    as a pose."""
    gt = truth_of(stream)
    truth_xy = CraterField.draw(SEED, 3 * FIELD_M).xy
    be = make_backend(name, _offset_start(stream))
    run_backend(be, stream.measurements)
    before = _err(be, gt)
    assert before > 0.35
    fix, lid = _anchor_fix(be, truth_xy, row=4)
    out = be.apply_fix(fix)
    assert out.accepted, out.reason
    lm = be.landmark_map("craters")
    k = int(np.flatnonzero(lm.ids == lid)[0])
    assert lm.catalog_row[k] == 4 and np.all(np.delete(lm.catalog_row, k) == -1)
    off = lm.xyz_world_m[k, :2] - fix.anchors[0].xy_m
    # the crater within 3 sigma of its entry, and its covariance no larger than the entry's and its own
    assert float(off @ np.linalg.solve(lm.cov_world_m2[k, :2, :2], off)) < 11.8
    assert np.linalg.norm(off) < 0.2
    assert _err(be, gt) < 0.5 * before
    extra = be.stats().extra
    assert extra["n_anchor_fixes"] == 1 and extra["n_anchors"] == 1
    again, _ = _anchor_fix(be, truth_xy, lid=lid, row=4)
    out2 = be.apply_fix(again)
    assert not out2.accepted and "anchored already" in out2.reason
    gone = dataclasses.replace(fix, anchors=(dataclasses.replace(fix.anchors[0], landmark_id=10**6),))
    out3 = be.apply_fix(gone)  # taken as a pose: the rover is where the fix says, so it passes
    assert out3.accepted, out3.reason
    assert be.stats().extra["n_anchor_fixes"] == 1 and be.stats().extra["n_anchors"] == 1


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_anchors_off_take_the_fix_as_a_pose(stream, name):
    truth_xy = CraterField.draw(SEED, 3 * FIELD_M).xy
    section = "fix_gate" if name == "ekf" else "fixes"
    be = make_backend(name, _offset_start(stream), {section: {"anchors": False}})
    run_backend(be, stream.measurements)
    fix, _ = _anchor_fix(be, truth_xy)
    assert be.apply_fix(fix).accepted
    assert be.stats().extra["n_anchor_fixes"] == 0
    assert np.all(be.landmark_map("craters").anchored_rows == -1)


@pytest.mark.parametrize("sigmas", [4.0, 0.0])
def test_the_ekf_takes_a_far_anchor_its_covariance_allows(stream, sigmas):
    """Started 4.5 m off with a 3 m sigma, the crater map is 4.5 m off its entries and the filter
    knows it: the anchor's distance gate opens with the landmark's own spread (4 sigma), so the
    entry goes on; with the sigmas off the reference design's 3 m refuse it."""
    gt = truth_of(stream)
    truth_xy = CraterField.draw(SEED, 3 * FIELD_M).xy
    T = stream.initial.T_world_base.copy()
    T[0, 3] += 4.5
    start = PoseEstimate(stream.initial.t, T, np.diag([3.0**2, 3.0**2, 0.01**2, 1e-6, 1e-6, 1e-4]))
    be = make_backend("ekf", start, {"fix_gate": {"distance_sigmas": sigmas}})
    run_backend(be, stream.measurements)
    before = _err(be, gt)
    assert before > 4.0
    fix, _ = _anchor_fix(be, truth_xy)
    out = be.apply_fix(fix)
    if sigmas > 0:
        assert out.accepted, out.reason
        assert be.stats().extra["n_anchor_fixes"] == 1 and _err(be, gt) < 0.5
    else:
        assert not out.accepted and out.reason.startswith("distance gate (anchor)") and "> 3.00 m" in out.reason
        assert _err(be, gt) == before


def test_the_ekf_keeps_an_anchor_through_a_late_fix_replay(stream):
    """The anchor is in the EKF's history: a late pose fix rolls back past it and replays it."""
    gt = truth_of(stream)
    truth_xy = CraterField.draw(SEED, 3 * FIELD_M).xy
    be = make_backend("ekf", _offset_start(stream))
    run_backend(be, stream.measurements)
    fix, lid = _anchor_fix(be, truth_xy, row=2)
    assert be.apply_fix(fix).accepted
    t_now = be.estimate().t
    T = gt.T_world_base[int(np.searchsorted(gt.t, t_now - 5.0))]
    late = GlobalFix(t_now - 5.0, t_now, T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])),
                     np.diag([0.15**2, 0.15**2, 0.01**2]))
    assert be.apply_fix(late).accepted
    lm = be.landmark_map("craters")
    assert lm.catalog_row[lm.ids == lid].tolist() == [2]
    extra = be.stats().extra
    assert extra["n_late_fixes"] >= 1 and extra["n_anchors_lost_in_replay"] == 0


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_an_anchor_with_a_height_also_sets_the_height(stream, name):
    """A fix with a terrain height: the entries on the landmarks and its z on the pose (started
    with a 1 m height sigma, so that a height 0.5 m off is no outlier)."""
    truth_xy = CraterField.draw(SEED, 3 * FIELD_M).xy
    be = make_backend(name, _offset_start(stream, sigma_z_m=1.0))
    run_backend(be, stream.measurements)
    fix, _ = _anchor_fix(be, truth_xy)
    z_before = float(be.estimate().position_m[2])
    fix = dataclasses.replace(fix, height=FixHeight(z_before + 0.5, 0.05**2, np.zeros(3)))
    assert be.apply_fix(fix).accepted
    assert be.stats().extra["n_anchor_fixes"] == 1
    assert float(be.estimate().position_m[2]) == pytest.approx(z_before + 0.5, abs=0.15)


def test_height_only_keeps_the_height_and_drops_the_rest():
    h = FixHeight(3.0, 0.04, np.array([0.01, 0.0, 0.0]))
    a = CatalogAnchor("craters", 1, 0, [1.0, 2.0], np.eye(2) * 0.01)
    fix = GlobalFix(1.0, 2.0, 5.0, 6.0, 0.1, np.diag([0.04, 0.04, 0.01]), height=h, anchors=(a,), source="craters")
    ho = fix.height_only()
    assert ho.anchors == () and ho.height.z_m == 3.0 and ho.height.var_m2 == 0.04
    assert ho.source == ""  # the terrain model's height shares no catalog error
    assert np.all(np.diag(ho.cov_xyyaw)[:2] >= 1e6)
    assert fix.planar().height_only() is None
    with pytest.raises(MeasurementError, match="cov_xy"):
        CatalogAnchor("craters", 1, 0, [1.0, 2.0], np.zeros((2, 2)))
    with pytest.raises(MeasurementError, match="catalog_row"):
        CatalogAnchor("craters", 1, -1, [1.0, 2.0], np.eye(2))
    with pytest.raises(MeasurementError, match="xy_m"):
        CatalogAnchor("craters", 1, 0, [np.nan, 2.0], np.eye(2))
    with pytest.raises(MeasurementError, match="anchors"):
        GlobalFix(1.0, 2.0, 5.0, 6.0, 0.1, np.eye(3), anchors=("row 3",))


# the relocalizer's side: one crater 12 m ahead, mapped DRIFT off its entry
CRATER, DRIFT = np.array([110.0, 48.0]), np.array([1.2, -0.8])


def _scene(anchored: int = -1):
    T = np.eye(4)
    T[:2, 3] = CRATER - np.array([12.0, 3.0]) + DRIFT
    est = PoseEstimate(100.0, T, np.diag([0.25, 0.25, 0.01, 1e-4, 1e-4, 1e-5]))
    cov = np.eye(3) * 0.15**2
    cov[:2, :2] += est.cov[:2, :2]
    lmap = LandmarkMap(np.array([7]), np.array([[*(CRATER + DRIFT), 0.0]]), cov[None], np.array([8.0]),
                       np.array([6]), "craters", catalog_row=np.array([anchored]))
    rng = np.random.default_rng(5)
    far = rng.uniform(-400, 400, (40, 2))
    far = far[np.linalg.norm(far - CRATER, axis=1) > 150]
    cat = RockCatalog(np.vstack([CRATER, far]), np.concatenate([[8.2], rng.uniform(1.0, 6.0, len(far))]),
                      np.ones(len(far) + 1))
    return est, lmap, cat


def _reloc(cat, **kw):
    return CraterRelocalizer(cat, {"min_new_observations": 0, "min_travel_m": 0.0, "min_turn_deg": 0.0, **kw})


def test_the_relocalizer_names_the_crater_and_its_entry():
    est, lmap, cat = _scene()
    rl = _reloc(cat, anchor_landmarks=True)
    att = rl.attempt({"craters": lmap}, est)
    assert att.status == "fix" and att.single
    (a,) = att.fix.anchors
    assert (a.kind, a.landmark_id, a.catalog_row) == ("craters", 7, 0)
    np.testing.assert_allclose(a.xy_m, CRATER)
    # the entry's own error only: 0.2 m and 0.06 of its 8.2 m in quadrature, neither the
    # matcher's sigma (the rover's side too) nor the inflation
    np.testing.assert_allclose(a.cov_xy, np.eye(2) * (0.2**2 + (0.06 * 8.2) ** 2), rtol=1e-9)
    assert np.sqrt(a.cov_xy[0, 0]) < np.sqrt(att_off_cov(cat, lmap, est)[0, 0])
    # off (the default): the same fix without anchors
    att_off = _reloc(cat).attempt({"craters": lmap}, est)
    assert att_off.status == "fix" and att_off.fix.anchors == ()
    # a wrong fix (the wrong-fix experiment) moves the pose: it must not carry the right entries
    wrong = WrongFixes(_reloc(cat, anchor_landmarks=True), WrongFixesConfig(fraction=1.0, offset_m=10.0), window=(0.0, 1e9), seed=0)
    watt = wrong.attempt({"craters": lmap}, est)
    assert watt.fix is not None and watt.fix.anchors == () and wrong.n_wrong == 1


def att_off_cov(cat, lmap, est):
    return _reloc(cat).attempt({"craters": lmap}, est).fix.cov_xyyaw


def test_anchor_settings_are_checked():
    with pytest.raises(RelocalizerError, match="anchor_sigma_m"):
        _reloc(_scene()[2], anchor_landmarks=True, anchor_sigma_m=0.0, catalog_sigma_rel=0.0)


def test_an_anchored_crater_is_not_identified_again():
    est, lmap, cat = _scene(anchored=0)
    att = _reloc(cat).attempt({"craters": lmap}, est)
    assert att.fix is None and att.status == "too few landmarks"

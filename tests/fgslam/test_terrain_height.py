"""Heights from an orbital terrain model: the DEM's sampling and GeoTIFF reader, the height a fix
gets (value, covariance, spacing), the (x, y, yaw, z) fix model of both back-ends against
numerical derivatives, and seeded runs where heights bound a wrong start height."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _synth_stream import make_stream

from fgslam.backends.registry import make_backend
from fgslam.errors import InputFileError
from fgslam.fix_sources import ReplayedFixes
from fgslam.inputs import truth_of
from fgslam.io.dem_tif import read_dem
from fgslam.runner import run_backend
from fgslam.smoother.factors import fix_covariance, se2_residual
from fgslam.terrain_height import DemHeights, TerrainHeightConfig, TerrainHeightError, WithHeight, with_heights
from reloc.backend import PoseEstimate
from reloc.dem import Dem, DemError
from reloc.errors import MeasurementError
from reloc.measurements import FixHeight, GlobalFix

GEO_KEYS = (1, 1, 0, 4, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32767, 3076, 0, 1, 9001)


def plane_dem(a=0.1, b=-0.05, c=2.0, post=1.0, xmin=-50.0, ymax=50.0, n=100) -> Dem:
    """z = a x + b y + c sampled at the post centres."""
    x = xmin + (np.arange(n) + 0.5) * post
    y = ymax - (np.arange(n) + 0.5) * post
    X, Y = np.meshgrid(x, y)
    return Dem(a * X + b * Y + c, post, xmin, ymax)


def fix_at(x, y, t=10.0, cov=None, yaw=0.3) -> GlobalFix:
    cov = np.diag([0.1**2, 0.2**2, 0.01**2]) if cov is None else cov
    return GlobalFix(t, t + 2.0, x, y, yaw, cov, n_inliers=8)


# -- the model -----------------------------------------------------------------------------------

def test_a_plane_is_sampled_exactly_with_its_gradient():
    dem = plane_dem()
    for x, y in [(0.0, 0.0), (12.3, -7.9), (-49.5, 49.5), (49.5, -49.5)]:
        s = dem.sample(x, y)
        assert s is not None
        assert s.z_m == pytest.approx(0.1 * x - 0.05 * y + 2.0, abs=1e-9)
        assert np.allclose(s.grad, [0.1, -0.05], atol=1e-9)


def test_outside_the_posts_or_next_to_no_data_there_is_no_height():
    dem = plane_dem()
    assert dem.sample(-49.9, 0.0) is None  # west of the first post centre
    assert dem.sample(0.0, 60.0) is None
    z = np.array(dem.z_m)
    z[50, 50] = np.nan  # the post at x = 0.5, y = -0.5
    holed = Dem(z, 1.0, -50.0, 50.0)
    assert holed.sample(0.7, -0.2) is None
    assert holed.sample(5.0, 5.0) is not None


@pytest.mark.parametrize("z, post, match", [
    (np.zeros(5), 1.0, "2D grid"), (np.zeros((3, 3)), 0.0, "post"), (np.full((3, 3), np.nan), 1.0, "no finite"),
    (np.array([[0.0, np.inf], [0.0, 0.0]]), 1.0, "infinite"),
])
def test_a_malformed_model_is_refused(z, post, match):
    with pytest.raises(DemError, match=match):
        Dem(z, post, 0.0, 0.0)


# -- the GeoTIFF reader --------------------------------------------------------------------------

def write_tif(path, z, post, xmin, ymax, nodata="nan", georef=True, dtype=np.float32):
    import tifffile

    tags = []
    if georef:
        tags = [(33550, "d", 3, (post, post, 0.0), False), (33922, "d", 6, (0.0, 0.0, 0.0, xmin, ymax, 0.0), False),
                (34735, "H", len(GEO_KEYS), GEO_KEYS, False)]
    if nodata is not None:
        tags.append((42113, "s", 0, nodata, False))
    tifffile.imwrite(path, z.astype(dtype), extratags=tags, tile=(16, 16) if min(z.shape) >= 16 else None)


def test_a_geotiff_reads_back_with_its_georeference_and_no_data(tmp_path):
    dem = plane_dem(post=2.0, xmin=100.0, ymax=-20.0, n=40)
    z = np.array(dem.z_m, dtype=np.float32)
    z[0, :5] = np.nan
    write_tif(tmp_path / "dem.tif", z, 2.0, 100.0, -20.0)
    back = read_dem(tmp_path / "dem.tif")
    assert back.post_m == 2.0 and back.extent == (100.0, 180.0, -100.0, -20.0)
    s = back.sample(131.0, -57.0)
    assert s.z_m == pytest.approx(0.1 * 131.0 - 0.05 * -57.0 + 2.0, abs=1e-4)
    assert back.sample(102.0, -21.5) is None  # next to the NaN posts


def test_a_numeric_no_data_value_becomes_nan(tmp_path):
    z = np.full((20, 20), 5.0)
    z[3, 3] = -9999.0
    write_tif(tmp_path / "dem.tif", z, 1.0, 0.0, 20.0, nodata="-9999")
    back = read_dem(tmp_path / "dem.tif")
    assert np.isnan(back.z_m[3, 3]) and np.nanmax(back.z_m) == 5.0


@pytest.mark.parametrize("case, match", [("missing", "not found"), ("text", "readable GeoTIFF"),
                                         ("nogeo", "georeference"), ("rgb", "one band")])
def test_a_bad_dem_file_is_named_with_its_problem(tmp_path, case, match):
    path = tmp_path / "dem.tif"
    if case == "text":
        path.write_text("not a tiff")
    elif case == "nogeo":
        write_tif(path, np.zeros((20, 20)), 1.0, 0.0, 0.0, georef=False)
    elif case == "rgb":
        import tifffile

        tifffile.imwrite(path, np.zeros((20, 20, 3), np.uint8), photometric="rgb")
    with pytest.raises(InputFileError, match=match) as exc:
        read_dem(path)
    assert str(path) in str(exc.value)


# -- the height of a fix -------------------------------------------------------------------------

def test_a_fix_gets_the_terrain_height_with_its_propagated_covariance():
    dem = plane_dem(a=0.2, b=0.1)
    cfg = TerrainHeightConfig(sigma_m=0.15, correlation_m=25.0, base_height_m=0.15)
    C = np.array([[0.04, 0.01, 0.001], [0.01, 0.09, -0.002], [0.001, -0.002, 0.0004]])
    f = DemHeights(dem, cfg).attach(fix_at(3.0, 4.0, cov=C))
    g = np.array([0.2, 0.1])
    assert f.height.z_m == pytest.approx(0.2 * 3 + 0.1 * 4 + 2.0 + 0.15 / math.sqrt(1 + g @ g), abs=1e-9)
    assert f.height.var_m2 == pytest.approx(0.15**2 + g @ C[:2, :2] @ g)
    assert np.allclose(f.height.cov_xyyaw, g @ C[:2, :])
    # the (x, y, yaw, z) covariance is the linear image of (x, y, yaw, DEM error): sample it
    rng = np.random.default_rng(0)
    e = rng.multivariate_normal(np.zeros(3), C, 200_000)
    z = e[:, :2] @ g + 0.15 * rng.standard_normal(len(e))
    assert np.allclose(np.cov(np.column_stack([e, z]).T), f.cov, atol=8e-4)  # sampling error ~3e-4 on the variances
    assert np.allclose(f.measured[:3], f.xyyaw) and f.planar().height is None


def test_heights_are_spaced_by_the_dem_errors_correlation_and_need_data_and_a_gentle_slope():
    heights = DemHeights(plane_dem(), TerrainHeightConfig(correlation_m=25.0))
    got = [heights.attach(fix_at(x, 0.0)).height is not None for x in (-40.0, -30.0, -15.0, -14.0, 20.0)]
    assert got == [True, False, True, False, True]
    assert heights.attach(fix_at(80.0, 0.0)).height is None  # off the model
    steep = DemHeights(plane_dem(a=1.0), TerrainHeightConfig())
    assert steep.attach(fix_at(0.0, 0.0)).height is None
    assert heights.counts() == {"attached": 3, "too_close": 2, "no_data": 1, "too_steep": 0}
    assert steep.counts()["too_steep"] == 1


def test_settings_are_checked_naming_the_key():
    with pytest.raises(TerrainHeightError, match="sigma_m"):
        TerrainHeightConfig(sigma_m=0.0)
    with pytest.raises(TerrainHeightError, match="correlation_m"):
        TerrainHeightConfig(correlation_m=-1.0)


def test_a_height_whose_covariance_is_not_positive_definite_is_refused():
    with pytest.raises(MeasurementError, match="positive definite"):
        GlobalFix(1.0, 2.0, 0.0, 0.0, 0.0, np.diag([0.01, 0.01, 0.001]), height=FixHeight(0.0, 0.01, [0.5, 0.0, 0.0]))
    with pytest.raises(MeasurementError, match="var_m2"):
        FixHeight(0.0, 0.0, [0.0, 0.0, 0.0])


def test_relocalizers_carry_heights_only_with_a_model_and_the_setting_on():
    class Producer:
        kinds, period_s, config, build_time_s, catalog = ("rocks",), 5.0, None, 0.0, "the catalog"

    dem = plane_dem()
    assert with_heights([Producer()], None, TerrainHeightConfig())[0].__class__ is Producer
    assert with_heights([Producer()], dem, TerrainHeightConfig(enabled=False))[0].__class__ is Producer
    wrapped = with_heights([Producer(), Producer()], dem, TerrainHeightConfig())
    assert all(isinstance(w, WithHeight) for w in wrapped) and wrapped[0].heights is wrapped[1].heights
    assert wrapped[0].kinds == ("rocks",) and wrapped[0].period_s == 5.0 and wrapped[0].catalog == "the catalog"


# -- the fix model with a height -----------------------------------------------------------------

def _exp(xi):
    import gtsam

    return gtsam.Pose3.Expmap(xi).matrix()


def test_the_smoother_residual_with_a_height_matches_central_differences():
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = _exp(rng.normal(0, [0.2, 0.2, 2.0, 5.0, 5.0, 1.0]))
        target = np.array([*rng.normal(0, 1, 2), rng.uniform(-3, 3), rng.normal(0, 1)])
        r, H = se2_residual(T, target)
        assert r.shape == (4,) and H.shape == (4, 6)
        assert r[3] == pytest.approx(T[2, 3] - target[3])
        num = np.zeros((4, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-6
            num[:, k] = (se2_residual(T @ _exp(d), target)[0] - se2_residual(T @ _exp(-d), target)[0]) / 2e-6
        assert np.allclose(H, num, atol=1e-6)
        assert np.allclose(se2_residual(T, target[:3])[1], H[:3])  # the planar rows are unchanged
    assert fix_covariance(T, np.eye(6) * 1e-4, np.eye(4) * 0.01).shape == (4, 4)


def test_the_ekf_fix_model_with_a_height_matches_central_differences():
    from ekf.updates import fix_model
    from reloc.geometry import exp_so3

    rng = np.random.default_rng(4)
    for _ in range(20):
        p, R = rng.normal(0, 5, 3), exp_so3(rng.normal(0, [0.2, 0.2, 2.0]))
        h, H = fix_model(p, R, height=True)
        assert h[3] == p[2]
        num = np.zeros((4, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-6
            hp = fix_model(p + d[:3], exp_so3(d[3:]) @ R, height=True)[0]
            hm = fix_model(p - d[:3], exp_so3(-d[3:]) @ R, height=True)[0]
            num[:, k] = hp - hm
            num[2, k] = math.remainder(num[2, k], 2 * math.pi)
        assert np.allclose(H, num / 2e-6, atol=1e-6)


# -- seeded runs ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stream():
    return make_stream(seed=7, duration_s=40.0)


def _start_high(stream, dz: float = 0.6) -> PoseEstimate:
    T = stream.initial.T_world_base.copy()
    T[2, 3] += dz
    return PoseEstimate(stream.initial.t, T, np.diag([0.05**2, 0.05**2, 0.5**2, 1e-5, 1e-5, 1e-4]))


def _height_fixes(stream, sigma_z: float, heights: bool) -> list[GlobalFix]:
    gt = truth_of(stream)
    rng = np.random.default_rng(11)
    out = []
    for t in np.arange(4.0, 38.0, 4.0):
        k = int(np.searchsorted(gt.t, t))
        T = gt.T_world_base[k]
        C = np.diag([0.05**2, 0.05**2, 0.005**2])
        e = rng.multivariate_normal(np.zeros(3), C)
        h = FixHeight(T[2, 3] + sigma_z * rng.standard_normal(), sigma_z**2, np.zeros(3)) if heights else None
        out.append(GlobalFix(gt.t[k], gt.t[k] + 1.5, T[0, 3] + e[0], T[1, 3] + e[1],
                             float(np.arctan2(T[1, 0], T[0, 0])) + e[2], C, n_inliers=8, height=h))
    return out


@pytest.mark.parametrize("name", ["ekf", "isam2", "dr"])
def test_heights_bound_a_wrong_start_height_and_its_covariance_says_so(stream, name):
    """Started 0.6 m too high (claimed sigma 0.5 m), late fixes with heights of 0.1 m bring z to the
    truth, inside its own 3 sigma; the same fixes without heights leave it where it was."""
    gt = truth_of(stream)
    over = {"dr": {"use_fixes": True}}.get(name)
    z_err, z_sig = {}, {}
    for heights in (False, True):
        be = make_backend(name, _start_high(stream), over)
        res = run_backend(be, stream.measurements, ReplayedFixes(_height_fixes(stream, 0.1, heights)))
        assert all(o.accepted for o in res.outcomes), [o.reason for o in res.outcomes if not o.accepted]
        e = be.estimate()
        k = min(int(np.searchsorted(gt.t, e.t)), len(gt.t) - 1)
        z_err[heights], z_sig[heights] = e.position_m[2] - gt.positions_m[k, 2], math.sqrt(e.cov[2, 2])
    assert abs(z_err[False]) > 0.4
    assert abs(z_err[True]) < 0.15 and abs(z_err[True]) < 3 * z_sig[True]
    assert z_sig[True] < 0.5 * z_sig[False]


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_a_height_far_off_is_refused_and_the_fix_kept_planar(stream, name):
    gt = truth_of(stream)
    be = make_backend(name, stream.initial)
    run_backend(be, stream.measurements)
    t = be.estimate().t - 3.0
    k = int(np.searchsorted(gt.t, t))
    T = gt.T_world_base[k]
    fix = GlobalFix(gt.t[k], be.estimate().t, T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0])),
                    np.diag([0.5**2, 0.5**2, 0.05**2]), n_inliers=8, height=FixHeight(T[2, 3] + 5.0, 0.1**2, np.zeros(3)))
    z0 = be.estimate().position_m[2]
    out = be.apply_fix(fix)
    assert out.accepted, out.reason
    assert out.fix.height is not None  # the outcome names the fix as it was given
    assert be.stats().extra["n_heights_refused"] == 1
    assert abs(be.estimate().position_m[2] - z0) < 0.05  # z not pulled 5 m up


def test_a_comparison_with_a_terrain_model_reports_the_fixes_heights(tmp_path):
    """The reference pass's fixes carry heights (spaced by the correlation length), every variant
    gets the same ones, and results.json, fixes.csv and the table report them."""
    import csv
    import json

    from _synth_stream import NearestNeighbourMatcher

    from fgslam.compare import CompareConfig, compare_world, relocalizer_set
    from fgslam.outputs import write_comparison, write_fixes_csv
    from fgslam.relocalizer import Relocalizer

    inputs = make_stream(seed=7, duration_s=40.0)
    inputs.dem = plane_dem(a=0.0, b=0.0, c=0.0)  # the synthetic ground is flat at z = 0
    cfg = CompareConfig(backends=("dr",), reference_backend="dr", backend_overrides={"dr": {"use_fixes": True}},
                        workers=1, terrain_height=TerrainHeightConfig(correlation_m=2.0, base_height_m=0.0))
    assert all(isinstance(r, WithHeight) for r in relocalizer_set(inputs, cfg))
    reloc = Relocalizer(inputs.catalog, cfg.relocalizer, matcher=NearestNeighbourMatcher(inputs.catalog.xy_m))
    heights = DemHeights(inputs.dem, cfg.terrain_height)
    wc = compare_world(inputs, cfg, relocalizers=[WithHeight(reloc, heights)])
    fixes = [a.fix for a in wc.attempts if a.fix is not None]
    with_h = [f for f in fixes if f.height is not None]
    assert 0 < len(with_h) < len(fixes) and heights.n_too_close > 0
    assert all(f.height.z_m == 0.0 for f in with_h)
    run = wc.runs["dr_reloc"]
    assert [o.fix for o in run.outcomes] == [f for f in fixes if f.t_recv <= run.t_end]
    write_comparison(tmp_path, [wc], cfg, rrd=False)
    h = json.loads((tmp_path / "results.json").read_text())["worlds"][0]["runs"]["dr_reloc"]["fixes"]["heights"]
    assert h["n"] == len(with_h) and h["error_rmse_m"] < 1e-6
    assert f"| Fix heights from the DEM (n / z RMSE m / NEES) | {len(with_h)} / 0.000 / 0.00 |" in (tmp_path / "table.md").read_text()
    rows = list(csv.DictReader(write_fixes_csv(tmp_path / "fixes.csv", run, wc.gt).open()))
    assert sum(r["z_m"] != "" for r in rows) == len([o for o in run.outcomes if o.fix.height is not None])
    assert all(abs(float(r["error_z_m"])) < 1e-6 for r in rows if r["z_m"])

"""The simulator's crater rims (sim.sensors.craters): what is in view, partial rims, the
reported covariance against the drawn errors, and the tiled stream's crater frames."""

from __future__ import annotations

import numpy as np
import pytest

from reloc.craters import CraterObservations
from sim.config import CraterSensorConfig, StereoConfig
from sim.craters import Craters
from sim.sensors.craters import crater_bias, observe_craters
from sim.sensors.stereo import StereoBias, StereoCamera

ST = StereoConfig()
CAM = StereoCamera.from_config(ST)
NO_BIAS = StereoBias(np.zeros(0), np.eye(3), 1.0)


def _see(craters: Craters, rng, cfg: CraterSensorConfig | None = None, yaw: float = 0.0, offsets=None):
    cfg = cfg or CraterSensorConfig(recall_fresh=1.0)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    off = np.zeros((len(craters), 3)) if offsets is None else offsets
    return observe_craters(craters, np.zeros(len(craters)), T, 0.0, cfg, ST, CAM, NO_BIAS, off, rng)


def test_whole_rims_in_view_are_seen_and_what_is_behind_or_far_is_not():
    c = Craters([[12.0, 0.0], [-12.0, 0.0], [60.0, 0.0], [8.0, 3.0]], [4.0, 4.0, 4.0, 0.5], [0.0] * 4, [1, 2, 3, 4])
    obs, ids = _see(c, np.random.default_rng(0))
    assert isinstance(obs, CraterObservations) and list(ids) == [1]  # behind, beyond range, too small: unseen
    assert obs.completeness[0] == 1.0 and abs(obs.size_m[0] - 4.0) < 0.5
    assert np.allclose(obs.xyz_base_m[0], [12.0, 0.0, 0.0], atol=0.5)


def test_a_crater_larger_than_the_view_is_a_partial_rim_with_a_long_axis():
    """A 30 m crater whose near rim is 7 m ahead: only an arc is in view; the centre is uncertain
    along the line to it (the arc's axis), much less across, and the diameter with it."""
    big = Craters([[22.0, 0.0]], [30.0], [0.0], [7])
    small = Craters([[14.0, 0.0]], [6.0], [0.0], [8])
    rng = np.random.default_rng(1)
    cfg = CraterSensorConfig(recall_fresh=1.0, centre_bias_frac=0.0)  # the fit's share alone
    ob, _ = _see(big, rng, cfg)
    os_, _ = _see(small, rng, cfg)
    assert 0.15 <= ob.completeness[0] < 0.5 and os_.completeness[0] == 1.0
    w, v = np.linalg.eigh(ob.cov_base_m2[0][:2, :2])
    assert abs(v[0, 1]) > 0.95  # the long axis is along x (towards the centre)
    assert w[1] > 2.5 * w[0]
    ws = np.linalg.eigvalsh(os_.cov_base_m2[0][:2, :2])
    assert ws[1] < 1.5 * ws[0]  # a whole rim: nearly round
    assert ob.size_sigma_m[0] / 30.0 > 1.5 * os_.size_sigma_m[0] / 6.0


def test_reported_covariance_matches_the_drawn_errors():
    """Monte Carlo over seeded frames: NEES of the rim centre ~ 3 (offsets drawn too)."""
    rng = np.random.default_rng(2)
    c = Craters([[14.0, 3.0], [20.0, -6.0], [9.0, 2.0], [30.0, 0.0]], [5.0, 8.0, 2.0, 30.0], [0.0, 0.2, 0.0, 0.0],
                [11, 12, 13, 14])
    nees = []
    for k in range(300):
        off = crater_bias(k, c.id)  # a new run each time: the per-crater offsets are drawn too
        obs, ids = _see(c, rng, offsets=off)
        for i, cid in enumerate(ids):
            e = obs.xyz_base_m[i] - np.array([*c.xy_m[cid - 11], 0.0])
            nees.append(e @ np.linalg.solve(obs.cov_base_m2[i], e))
    assert len(nees) > 600
    assert 2.6 < np.mean(nees) < 3.4


def test_offsets_are_fixed_per_crater_and_degraded_rims_are_missed_more():
    assert np.array_equal(crater_bias(3, np.array([5, 9])), crater_bias(3, np.array([5, 9])))
    assert not np.array_equal(crater_bias(3, np.array([5])), crater_bias(4, np.array([5])))
    rng = np.random.default_rng(4)
    c = Craters([[12.0, 0.0], [12.0, 6.0]], [4.0, 4.0], [0.0, 1.0], [1, 2])
    cfg = CraterSensorConfig(recall_fresh=0.9, degradation_penalty=0.5)
    seen = np.zeros(2)
    for _ in range(400):
        _, ids = _see(c, rng, cfg)
        seen += np.isin([1, 2], ids)
    assert abs(seen[0] / 400 - 0.9) < 0.05 and abs(seen[1] / 400 - 0.45) < 0.07


@pytest.mark.parametrize("bad", [dict(min_completeness=0.0), dict(max_range_m=0.5), dict(recall_fresh=1.5)])
def test_bad_crater_sensor_settings_are_refused(bad):
    import dataclasses

    from sim.config import SimConfig, SimConfigError, validate

    cfg = SimConfig()
    cfg = dataclasses.replace(cfg, sensors=dataclasses.replace(cfg.sensors, craters=CraterSensorConfig(**bad)))
    with pytest.raises(SimConfigError, match="sensors.craters"):
        validate(cfg)

"""Crater observations and the rim-fit model behind their covariance (reloc.craters)."""

from __future__ import annotations

import numpy as np
import pytest

from reloc.craters import CraterObservations, arc_fraction, fit_rim, rim_fit_covariance
from reloc.errors import MeasurementError


def _obs(**kw):
    base = dict(t=1.0, xyz_base_m=[[10.0, 1.0, -0.5]], cov_base_m2=np.eye(3)[None] * 0.04, size_m=[4.0],
                size_sigma_m=[0.2], completeness=[0.8], score=[0.9])
    base.update(kw)
    return CraterObservations(**base)


def test_observations_are_validated_and_frozen():
    o = _obs()
    assert len(o) == 1 and o.xyz_base_m.shape == (1, 3) and not o.xyz_base_m.flags.writeable
    assert len(CraterObservations(0.0, np.zeros((0, 3)), np.zeros((0, 3, 3)), [], [], [], [])) == 0
    for kw, msg in ((dict(completeness=[0.0]), "completeness"), (dict(completeness=[1.2]), "completeness"),
                    (dict(size_sigma_m=[0.0]), "size_sigma_m"), (dict(cov_base_m2=-np.eye(3)[None]), "positive definite"),
                    (dict(xyz_base_m=[[np.nan, 0, 0]]), "NaN"), (dict(score=[1.5]), "score"),
                    (dict(size_m=[4.0, 5.0]), "shape")):
        with pytest.raises(MeasurementError, match=msg):
            _obs(**kw)


def test_a_whole_rim_fixes_centre_and_radius_to_the_textbook_sigmas():
    a = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    C = rim_fit_covariance(a, 0.1)
    assert np.allclose(np.diag(C), [0.01 * 2 / 40, 0.01 * 2 / 40, 0.01 / 40])
    assert np.allclose(C - np.diag(np.diag(C)), 0.0, atol=1e-12)


def test_a_partial_rim_is_uncertain_along_its_axis_and_in_radius_together():
    """An arc centred on +x: the centre's x (the arc's axis) and the radius trade off; y stays good;
    both grow steeply as the arc shortens."""
    out = []
    for half_deg in (180, 90, 45, 25):
        a = np.deg2rad(np.linspace(-half_deg, half_deg, 40, endpoint=half_deg < 180))
        C = rim_fit_covariance(a, 0.1)
        out.append(C)
        if half_deg < 180:
            # towards the arc with a smaller radius fits as well: x and r anti-correlated
            assert C[0, 0] > C[1, 1] and C[0, 2] / np.sqrt(C[0, 0] * C[2, 2]) < -0.85
    sx = [np.sqrt(C[0, 0]) for C in out]
    assert all(b > 1.5 * a for a, b in zip(sx, sx[1:]))  # steeper than linear
    assert sx[-1] > 20 * sx[0]


def test_fit_rim_recovers_a_circle_and_its_covariance_is_what_monte_carlo_gives():
    rng = np.random.default_rng(3)
    a = np.deg2rad(np.linspace(-70, 70, 60))
    c_true, r_true, sigma = np.array([5.0, -2.0]), 3.0, 0.05
    fits = []
    for _ in range(300):
        rr = r_true + sigma * rng.standard_normal(len(a))
        fits.append(fit_rim(c_true + rr[:, None] * np.column_stack([np.cos(a), np.sin(a)]), sigma))
    est = np.array([[*f.centre_m, f.radius_m] for f in fits])
    assert np.allclose(est.mean(axis=0), [*c_true, r_true], atol=0.02)
    emp = np.cov(est.T)
    pred = fits[0].cov
    assert np.allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(pred)), rtol=0.2)
    assert abs(fits[0].arc_fraction - 140 / 360) < 0.01


def test_fit_rim_and_arc_fraction_refuse_or_report_degenerate_input():
    with pytest.raises(MeasurementError, match="at least 3"):
        fit_rim(np.zeros((2, 2)), 0.1)
    with pytest.raises(MeasurementError, match="at least 3"):
        rim_fit_covariance([0.0, 1.0], 0.1)
    assert arc_fraction([]) == 0.0 and arc_fraction(np.linspace(0, 2 * np.pi, 36, endpoint=False)) > 0.97

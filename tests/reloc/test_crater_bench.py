"""The crater Table I of ``fgslam bench detect --landmark crater``: disc matching with ignore
craters and size rows, precision / recall / AP, centre and diameter errors, the threshold."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.bench.detect_craters import evaluate_craters, match_craters, pick_crater_threshold
from reloc.detector import CraterDetections
from sim.crater_datasets import CraterLabels


def _labels(c, d, ignore=None) -> CraterLabels:
    c = np.reshape(np.asarray(c, float), (-1, 2))
    return CraterLabels(c, np.asarray(d, float), np.zeros(len(c), bool) if ignore is None else np.asarray(ignore))


def _dets(c, d, s) -> CraterDetections:
    return CraterDetections(np.reshape(np.asarray(c, np.float32), (-1, 2)), np.asarray(d, np.float32), np.asarray(s, np.float32))


def test_match_craters_greedy_with_ignore_and_size_range():
    lab = _labels([[10, 10], [50, 10], [90, 10], [130, 10]], [10, 20, 3, 40], ignore=[False, False, True, False])
    det = _dets([[10, 10], [11, 10], [51, 11], [90, 10], [200, 200], [131, 10]], [10, 10, 21, 3.5, 9, 38],
                [0.6, 0.9, 0.8, 0.7, 0.5, 0.4])
    m, j = match_craters(det, lab, 0.5)
    # the higher-scored near-duplicate takes the first crater; the exact one is then a false positive
    assert list(m) == [0, 1, 1, -1, 0, 1] and list(j[m == 1]) == [0, 1, 3]
    # in the 8-16 px row: craters of 20 and 40 px act as ignore; detections of other sizes
    # that match nothing are not counted
    m, _ = match_craters(det, lab, 0.5, (8.0, 16.0))
    assert list(m) == [0, 1, -1, -1, 0, -1]


def test_evaluate_craters_errors_and_rows():
    lab = [_labels([[20, 20], [60, 20], [100, 20]], [10, 20, 30])]
    # centre off by 1 px (0.1 D) and 2 % small; exact; missed; one false positive
    det = [_dets([[21, 20], [60, 20], [150, 150]], [9.8, 20, 12], [0.9, 0.8, 0.7])]
    r = evaluate_craters(det, lab, 0.5, (0.0, np.inf))
    assert r["n_true"] == 3 and r["n_detections"] == 3
    assert r["precision"] == pytest.approx(2 / 3) and r["recall"] == pytest.approx(2 / 3)
    assert r["centre_error_d"] == pytest.approx(0.05) and r["diameter_error"] == pytest.approx(0.01)
    assert r["map50_95"] <= r["map50"]
    hi = evaluate_craters(det, lab, 0.85, (0.0, np.inf))
    assert hi["precision"] == 1.0 and hi["recall"] == pytest.approx(1 / 3)
    big = evaluate_craters(det, lab, 0.5, (16.0, np.inf))  # the 10 px crater and 12 px detection drop out
    assert big["n_true"] == 2 and big["precision"] == 1.0 and big["recall"] == 0.5


def test_pick_crater_threshold_balances_the_goals():
    rng = np.random.default_rng(0)
    c = np.column_stack([np.arange(20) * 30.0 + 15, np.full(20, 15.0)])
    lab = [_labels(c, np.full(20, 12.0))]
    fp = np.column_stack([np.arange(6) * 30.0 + 15, np.full(6, 100.0)])
    det = [_dets(np.vstack([c, fp]), np.full(26, 12.0), np.r_[rng.uniform(0.4, 1.0, 20), rng.uniform(0.0, 0.7, 6)])]
    thr = pick_crater_threshold(det, lab, 0.9, 0.8, 8.0)
    r = evaluate_craters(det, lab, thr, (8.0, np.inf))
    best = min(r["precision"] - 0.9, r["recall"] - 0.8)
    for other in np.unique(det[0].score):
        o = evaluate_craters(det, lab, float(other), (8.0, np.inf))
        assert min(o["precision"] - 0.9, o["recall"] - 0.8) <= best + 1e-12


def test_scr_labels_ignore_the_craters_outside_the_ratio_bin():
    from fgslam.bench.detect_craters import scr_labels

    lab = [_labels([[20, 20], [60, 20], [100, 20], [140, 20]], [10, 20, 30, 3], ignore=[False, False, False, True])]
    scr = [np.array([0.5, 2.5, 7.0, np.nan])]
    out = scr_labels(lab, scr, 2.0, np.inf)[0]
    assert list(out.ignore) == [True, False, False, True] and out.diameters_px is lab[0].diameters_px
    det = [_dets([[20, 20], [60, 20]], [10, 20], [0.9, 0.8])]
    r = evaluate_craters(det, scr_labels(lab, scr, 2.0, np.inf), 0.5, (8.0, np.inf))
    # the detection of the faint crater counts neither way; the missed bright one counts
    assert r["n_true"] == 2 and r["precision"] == 1.0 and r["recall"] == 0.5
    assert scr_labels(lab, scr, 0.0, 1.0)[0].ignore.tolist() == [False, True, True, True]

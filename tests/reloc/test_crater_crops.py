"""Training crops of the crater detector: the photometric ignore rule (``min_scr``) changes the
targets, never the image, and faint craters become ignore regions, not negatives."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.train.craters import crop_sample, render_scenes


@pytest.fixture(scope="module")
def scene():
    return render_scenes(1, 7, "train", ground=True)[0]


def test_scenes_with_their_ground_are_the_same_scenes(scene):
    plain = render_scenes(1, 7, "train")[0]
    assert "ground" not in plain and scene["ground"].shape == scene["grey"].shape
    assert np.array_equal(plain["grey"], scene["grey"]) and np.array_equal(plain["diameters"], scene["diameters"])


def test_min_scr_moves_faint_targets_to_ignore_and_keeps_the_crop(scene):
    n_removed = 0
    for k in range(12):
        x0, c0, _, b0 = crop_sample(scene, np.random.default_rng(k), 128)
        x1, c1, _, b1 = crop_sample(scene, np.random.default_rng(k), 128, min_scr=2.0)
        assert np.array_equal(x0, x1)  # the same draws, the same image
        kept = {(round(float(u), 3), round(float(v), 3)) for u, v in c1}
        assert kept <= {(round(float(u), 3), round(float(v), 3)) for u, v in c0}
        removed = len(c0) - len(c1)
        assert len(b1) == len(b0) + removed  # every target left out is an ignore region
        n_removed += removed
    assert n_removed > 0  # a cratered scene always holds some craters the camera hides


def test_min_scr_needs_the_ground():
    plain = {"grey": np.zeros((64, 64), np.uint16), "centres": np.zeros((0, 2), np.float32),
             "diameters": np.zeros(0, np.float32), "visible": np.zeros(0, bool)}
    with pytest.raises(ValueError, match="ground"):
        crop_sample(plain, np.random.default_rng(0), 32, min_scr=1.5)

"""What a recording shows of the orbital image: tiles along the path, within a pixel budget that
grows with the path, cut where the image is (checked against the image's own pixels)."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.viz import orbital_tiles as OT

EXTENT = (-500.0, 500.0, -400.0, 400.0)  # 1000 x 800 m at 0.25 m/px: 4000 x 3200 px


@pytest.fixture(scope="module")
def image():
    # a ramp in x (red) and in y (green), so every tile's colour says where it was cut from
    H, W = 3200, 4000
    img = np.zeros((H, W, 3), dtype=np.uint8)
    img[:, :, 0] = np.linspace(0, 255, W)[None, :].astype(np.uint8)
    img[:, :, 1] = np.linspace(255, 0, H)[:, None].astype(np.uint8)  # first row at ymax
    return img


def _path(length_m: float) -> np.ndarray:
    x = np.linspace(-450.0, -450.0 + length_m, max(2, int(length_m)))
    return np.column_stack([x, 30.0 * np.sin(x / 80.0)])


def _pixels(view: OT.MapTiles) -> int:
    return sum(t.image.shape[0] * t.image.shape[1] for t in view.tiles)


@pytest.mark.parametrize("length_m", [100.0, 400.0, 850.0])
def test_tiles_cover_the_path_and_its_margin_within_the_budget(image, length_m):
    path = _path(length_m)
    view = OT.map_tiles(image, EXTENT, path)
    assert _pixels(view) <= OT.pixel_budget(path)
    assert view.gsd_m >= 0.25 - 1e-12  # never finer than the image
    assert view.covers(path).all()
    # the margin either side of the path is shown, ground 3 margins away is not
    side = np.column_stack([path[:, 0], path[:, 1] + OT.MARGIN_M * 0.95])
    assert view.covers(side[(side[:, 1] < EXTENT[3])]).all()
    far = np.column_stack([path[:, 0], path[:, 1] + 3.0 * OT.MARGIN_M + 1.5 * view.side_m])
    assert not view.covers(far).any()


def test_the_image_shown_grows_with_the_path_not_with_the_world(image):
    # the budget: a floor for short drives, then linear in the path's length, then a cap
    b = {L: OT.pixel_budget(_path(L)) for L in (50.0, 900.0, 1800.0, 3600.0)}
    assert b[50.0] == OT.MIN_IMAGE_PX
    assert b[1800.0] <= 2.02 * b[900.0] and b[3600.0] <= OT.MAX_IMAGE_PX  # (the wiggle: 2.005)
    # the tiles: within the budget of each length, far less than the whole image
    px = {L: _pixels(OT.map_tiles(image, EXTENT, _path(L), budget_px=OT.IMAGE_PX_PER_M * L)) for L in (200.0, 400.0, 800.0)}
    assert px[800.0] < 0.1 * image.shape[0] * image.shape[1]
    for L, n in px.items():
        assert 0.5 * OT.IMAGE_PX_PER_M * L < n <= OT.IMAGE_PX_PER_M * L


def test_each_tile_holds_the_pixels_of_its_extent(image):
    view = OT.map_tiles(image, EXTENT, _path(300.0))
    x0, x1, y0, y1 = EXTENT
    for t in view.tiles:
        tx0, tx1, ty0, ty1 = t.extent
        assert x0 <= tx0 < tx1 <= x1 and y0 <= ty0 < ty1 <= y1
        # the ramps' values at the tile's centre, from the tile and from the geometry
        h, w = t.image.shape[:2]
        red = float(t.image[h // 2, w // 2, 0])
        green = float(t.image[h // 2, w // 2, 1])
        assert red == pytest.approx(255.0 * (0.5 * (tx0 + tx1) - x0) / (x1 - x0), abs=3.0)
        assert green == pytest.approx(255.0 * (0.5 * (ty0 + ty1) - y0) / (y1 - y0), abs=3.0)
        # square pixels at the view's resolution
        assert (tx1 - tx0) / w == pytest.approx(view.gsd_m, rel=0.05)
        assert (ty1 - ty0) / h == pytest.approx(view.gsd_m, rel=0.05)


def test_without_a_path_the_whole_image_is_one_tile_within_the_largest_budget(image):
    view = OT.map_tiles(image, EXTENT, None)
    assert len(view.tiles) == 1
    t = view.tiles[0]
    assert t.extent == pytest.approx(EXTENT)
    assert t.image.shape[0] * t.image.shape[1] <= OT.MAX_IMAGE_PX
    assert view.covers(np.array([[-499.0, 399.0], [499.0, -399.0]])).all()


def test_a_small_image_is_shown_at_its_own_resolution():
    img = np.full((200, 300, 3), 128, dtype=np.uint8)
    view = OT.map_tiles(img, (0.0, 30.0, 0.0, 20.0), np.array([[5.0, 5.0], [25.0, 15.0]]))
    assert view.gsd_m == pytest.approx(0.1)
    assert _pixels(view) == 200 * 300  # every pixel, none resampled


def test_a_path_with_nan_or_outside_the_image_shows_what_lies_on_the_image(image):
    path = np.array([[np.nan, 0.0], [0.0, 0.0], [10.0, 0.0], [5000.0, 5000.0]])
    view = OT.map_tiles(image, EXTENT, path)
    assert view.covers(np.array([[0.0, 0.0], [10.0, 0.0]])).all()
    assert _pixels(view) <= OT.MAX_IMAGE_PX

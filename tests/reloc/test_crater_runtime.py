"""Crater detector runtime without the shipped weights: decoding, disc IoU and NMS, image
normalisation for any bit depth, the pyramid bands, tiled inference equal to whole-image
inference, the landmark registry, and clear errors for bad model files and images."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.train.targets import centre_targets
from reloc.detector import (
    CraterConfig,
    CraterDetector,
    DetectorConfig,
    DetectorError,
    ImageError,
    RockDetector,
    circle_iou_matrix,
    circle_nms,
    decode_craters,
    default_model_path,
    orbital_detector,
    orbital_landmarks,
)
from reloc.detector.image import half, normalised_grey
from reloc.errors import RelocError

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper

META = {"fgslam_layout": "crater-centernet-v1", "stride": "2", "input_size": "128,128", "score_threshold": "0.5"}


def _stub_model(tmp_path, name="stub.onnx", diameter_px=8.0, channels_in=1, n_out=4, in_rank=4, meta=None) -> str:
    """A crater-layout model: heat = the 2 x 2 average of the image, offsets 0.5, a constant
    diameter; its reach is one output cell, so tiles must reproduce the whole image exactly."""
    shape = ["N", channels_in, "H", "W"] if in_rank == 4 else ["N", "H", "W"]
    inp = helper.make_tensor_value_info("images", TensorProto.FLOAT, shape)
    out = helper.make_tensor_value_info("centernet", TensorProto.FLOAT, None)
    inits = [numpy_helper.from_array(np.float32(0.0).reshape(()), "zero"),
             numpy_helper.from_array(np.float32(0.5).reshape(()), "half"),
             numpy_helper.from_array(np.float32(np.log(diameter_px / 2.0)).reshape(()), "logd")]
    nodes = [helper.make_node("AveragePool", ["images"], ["heat"], kernel_shape=[2, 2], strides=[2, 2]),
             helper.make_node("Mul", ["heat", "zero"], ["z"]),
             helper.make_node("Add", ["z", "half"], ["off"]),
             helper.make_node("Add", ["z", "logd"], ["size"])]
    outs = ["heat", "off", "off", "size"] + ["size"] * (n_out - 4)
    nodes.append(helper.make_node("Concat", outs, ["centernet"], axis=1))
    if in_rank != 4:  # pooling needs an image: the output is just the input
        nodes = [helper.make_node("Mul", ["images", "zero"], ["centernet"])]
    graph = helper.make_graph(nodes, "crater_stub", [inp], [out], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in (META if meta is None else meta).items():
        model.metadata_props.add(key=k, value=v)
    path = tmp_path / name
    onnx.save(model, str(path))
    return str(path)


def _spots(h: int, w: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A dark image with ``n`` bright 2 x 2 blocks at random even positions, and their centres."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 20, np.uint8)
    cells = rng.choice((h // 8) * (w // 8), n, replace=False)  # one spot per 8 x 8 block at most
    ij = np.column_stack([4 * (cells // (w // 8)) + 1, 4 * (cells % (w // 8)) + 1])
    for i, j in ij:
        img[2 * i:2 * i + 2, 2 * j:2 * j + 2] = 220
    return img, np.column_stack([2 * ij[:, 1] + 1.0, 2 * ij[:, 0] + 1.0])


def test_decode_craters_round_trip():
    c = np.array([[20.3, 30.9], [100.0, 50.5], [7.2, 120.8]])
    d = np.array([[6.0], [31.5], [4.2]])
    t = centre_targets(c, d, np.zeros((0, 4)), 128, 160, 2, sigma_per_size=0.1)
    out = np.concatenate([t["heat"][None], t["reg"]])[None]
    assert out.shape == (1, 4, 64, 80)
    cc, dd, s = decode_craters(out, 2, 0.5, 100)
    order = np.argsort(cc[:, 0])
    assert np.allclose(cc[order], c[np.argsort(c[:, 0])], atol=1e-4)
    assert np.allclose(dd[order], d[np.argsort(c[:, 0]), 0], rtol=1e-5) and np.allclose(s, 1.0)
    # a training crop without any crater
    empty = centre_targets(np.zeros((0, 2)), np.zeros((0, 1)), np.array([[0, 0, 9, 9]]), 64, 64, 2, sigma_per_size=0.1)
    assert empty["reg"].shape == (3, 32, 32) and empty["heat"].max() == 0 and empty["weight"][:4, :4].max() == 0
    assert len(decode_craters(np.concatenate([empty["heat"][None], empty["reg"]])[None], 2, 0.5, 10)[2]) == 0


def test_circle_iou_and_nms():
    c = np.array([[0.0, 0.0], [0.0, 0.0], [100.0, 0.0], [3.0, 4.0]])
    d = np.array([10.0, 20.0, 10.0, 10.0])
    iou = circle_iou_matrix(c, d, c, d)
    assert np.allclose(np.diag(iou), 1.0)
    assert iou[0, 1] == pytest.approx(0.25)  # concentric, radius ratio 2
    assert iou[0, 2] == 0.0
    # discs of radius 5 at distance 5: lens area 2 r^2 acos(1/2) - (d/2) sqrt(4r^2 - d^2)
    r, dist = 5.0, 5.0
    lens = 2 * r**2 * np.arccos(dist / (2 * r)) - 0.5 * dist * np.sqrt(4 * r**2 - dist**2)
    assert iou[0, 3] == pytest.approx(lens / (2 * np.pi * r**2 - lens))
    score = np.array([0.9, 0.8, 0.7, 0.95])
    assert list(circle_nms(c, d, score, 0.3)) == [3, 0, 1, 2]  # IoUs 0.24 and 0.25 stay under 0.3
    assert list(circle_nms(c, d, score, 0.2)) == [3, 2]


@pytest.mark.parametrize("make", [
    lambda g: g.astype(np.uint8),
    lambda g: (g.astype(np.uint16) * 257),
    lambda g: (g.astype(np.float32) / 255.0 * 0.37 + 0.01),
    lambda g: np.repeat(g.astype(np.uint8)[:, :, None], 3, axis=2),
])
def test_normalisation_is_the_same_for_any_bit_depth(make):
    g = np.random.default_rng(1).integers(0, 256, (64, 80)).astype(np.float64)
    ref, _ = normalised_grey(g.astype(np.uint8))
    x, valid = normalised_grey(make(g))
    assert valid.all() and np.allclose(x, ref, atol=2e-3)
    assert np.percentile(x, 1) == pytest.approx(0.1, abs=0.01) and np.percentile(x, 99) == pytest.approx(0.9, abs=0.01)


def test_nodata_and_bad_images():
    g = np.random.default_rng(2).uniform(0, 1, (40, 40)).astype(np.float32)
    g[:10] = np.nan
    x, valid = normalised_grey(g)
    assert not valid[:10].any() and valid[10:].all() and np.isfinite(x).all()
    y, valid2 = normalised_grey(np.where(np.isnan(g), -9999.0, g), nodata=-9999.0)
    assert np.array_equal(valid, valid2) and np.allclose(x, y)
    with pytest.raises(ImageError, match="no valid pixel"):
        normalised_grey(np.full((8, 8), np.nan))
    with pytest.raises(ImageError, match="shape"):
        normalised_grey(np.zeros((8, 8, 5)))
    with pytest.raises(ImageError, match="shape"):
        normalised_grey(np.zeros(8))
    flat, _ = normalised_grey(np.full((8, 8), 7, np.uint16))
    assert np.all(flat == 0.5)
    assert half(np.ones((5, 7), np.float32)).shape == (3, 4)


def test_tiled_detection_equals_whole_image(tmp_path):
    img, centres = _spots(300, 420, 60)
    det_t = CraterDetector(_stub_model(tmp_path), config=DetectorConfig(tile_overlap_px=32))
    det_w = CraterDetector(_stub_model(tmp_path), config=DetectorConfig(tile=False))
    a, b = det_t.detect(img), det_w.detect(img)
    assert len(a) == len(b) == len(centres)
    oa, ob = np.lexsort(a.centers_px.T), np.lexsort(b.centers_px.T)
    assert np.allclose(a.centers_px[oa], b.centers_px[ob]) and np.allclose(a.score[oa], b.score[ob])
    assert np.allclose(np.sort(a.centers_px[:, 0]), np.sort(centres[:, 0]))
    assert np.allclose(a.diameters_px, 8.0)
    # the same detections from 16-bit and float versions of the image
    c16 = det_t.detect(img.astype(np.uint16) * 257)
    assert np.allclose(np.sort(c16.centers_px[:, 0]), np.sort(a.centers_px[:, 0]))


def test_pyramid_bands_and_levels(tmp_path):
    det = CraterDetector(_stub_model(tmp_path))
    assert det.levels((640, 640)) == 5 and det.levels((40, 2000)) == 1 and det.levels((160, 160)) == 3
    assert det.band(0, 5) == (0.0, 13.0) and det.band(1, 5) == (6.0, 13.0) and det.band(4, 5) == (6.0, 24.0)
    # a stub that reports 15 px craters: over the band of the finer levels, so they come from
    # the coarsest (level 2 of a 256 px image with max_diameter_px 64), at 4 x its diameter
    # and coordinates
    det30 = CraterDetector(_stub_model(tmp_path, "d30.onnx", diameter_px=15.0), crater=CraterConfig(max_diameter_px=64.0))
    img = np.full((256, 256), 20, np.uint8)
    img[96:112, 48:64] = 250
    d = det30.detect(img)
    assert det30.levels(img.shape) == 3
    assert len(d) == 1 and d.diameters_px[0] == pytest.approx(60.0)
    assert np.linalg.norm(d.centers_px[0] - [56.0, 104.0]) <= 6.0  # a plateau of 8 px output cells
    # nodata: a detection centred on an invalid pixel is dropped
    img_nd = img.astype(np.float32)
    centres = np.array([[52, 100], [60, 100], [52, 108], [60, 108]])  # the level-2 plateau's cells
    img_nd[centres[:, 1], centres[:, 0]] = np.nan
    assert len(det30.detect(img_nd)) == 0
    img_nd[centres[:, 1], centres[:, 0]] = -1.0
    assert len(det30.detect(img_nd)) == 1
    assert len(CraterDetector(_stub_model(tmp_path, "d30.onnx", diameter_px=15.0),
                              crater=CraterConfig(max_diameter_px=64.0, nodata=-1.0)).detect(img_nd)) == 0


def test_bad_crater_model_files(tmp_path):
    with pytest.raises(DetectorError, match="file not found"):
        CraterDetector(tmp_path / "missing.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(DetectorError, match="not a loadable ONNX model"):
        CraterDetector(garbage)
    with pytest.raises(DetectorError, match="expected 'crater-centernet-v1'"):
        CraterDetector(default_model_path("nadir"))  # a rock model
    with pytest.raises(DetectorError, match="expected 'crater-centernet-v1'"):
        CraterDetector(_stub_model(tmp_path, "nometa.onnx", meta={}))
    with pytest.raises(DetectorError, match="bad metadata"):
        CraterDetector(_stub_model(tmp_path, "badstride.onnx", meta={**META, "stride": "two"}))
    with pytest.raises(DetectorError, match="unusable stride"):
        CraterDetector(_stub_model(tmp_path, "stride3.onnx", meta={**META, "stride": "3"}))
    with pytest.raises(DetectorError, match="1 \\(grey\\) channel"):
        CraterDetector(_stub_model(tmp_path, "rgb.onnx", channels_in=3))
    with pytest.raises(DetectorError, match="N x C x H x W"):
        CraterDetector(_stub_model(tmp_path, "rank3.onnx", in_rank=3))
    with pytest.raises(DetectorError, match="output shape"):
        CraterDetector(_stub_model(tmp_path, "five.onnx", n_out=5))
    with pytest.raises(DetectorError, match="a crater model"):
        RockDetector(_stub_model(tmp_path, "asrock.onnx"))
    with pytest.raises(DetectorError, match="band_px"):
        CraterDetector(_stub_model(tmp_path), crater=CraterConfig(band_px=(30.0, 20.0)))
    assert issubclass(DetectorError, RelocError)


def test_bad_images_raise(tmp_path):
    det = CraterDetector(_stub_model(tmp_path))
    with pytest.raises(ImageError, match="shape"):
        det.detect(np.zeros((32, 32, 2), np.uint8))
    with pytest.raises(ImageError, match="no valid pixel"):
        det.detect(np.full((64, 64), np.nan, np.float32))
    flat = CraterDetector(_stub_model(tmp_path), config=DetectorConfig(score_threshold=0.6))
    assert len(flat.detect(np.full((64, 64), 9, np.uint8))) == 0  # flat (normalised to 0.5): no error


def test_registry(tmp_path):
    assert {"rock", "crater"} <= set(orbital_landmarks())
    assert isinstance(orbital_detector("crater", _stub_model(tmp_path)), CraterDetector)
    assert isinstance(orbital_detector("rock"), RockDetector)
    with pytest.raises(DetectorError, match="no orbital detector for landmark kind 'boulder'"):
        orbital_detector("boulder")

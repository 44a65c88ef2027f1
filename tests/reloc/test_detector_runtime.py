"""Detector runtime without the shipped weights: YOLO-layout decoding, NMS, tiling, the
training-target / decoding round trip, and clear errors for bad model files and images."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.train.targets import STRIDE, make_targets
from reloc.detector import DetectorConfig, DetectorError, Detections, RockDetector, decode_centernet, decode_yolo, iou_matrix, nms
from reloc.detector.runtime import _tile_starts
from reloc.errors import RelocError

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402


def _yolo_tensor(boxes_cxcywh, scores, nc: int = 2, n_anchor: int = 50, rng=None) -> np.ndarray:
    """A (1, 4 + nc, n_anchor) Ultralytics-style output with the given boxes, low noise elsewhere."""
    rng = rng or np.random.default_rng(0)
    out = np.zeros((1, 4 + nc, n_anchor), np.float32)
    out[0, :4] = rng.uniform(10, 50, (4, n_anchor))
    out[0, 4:] = rng.uniform(0, 0.05, (nc, n_anchor))
    for k, (b, s) in enumerate(zip(boxes_cxcywh, scores)):
        out[0, :4, k] = b
        out[0, 4:, k] = 0.0
        out[0, 4 + s[0], k] = s[1]
    return out


def test_decode_yolo_thresholds_and_suppresses_per_class():
    boxes = [(100, 100, 40, 20), (102, 101, 40, 20), (300, 50, 10, 10), (101, 100, 40, 20)]
    scores = [(0, 0.9), (0, 0.7), (1, 0.6), (1, 0.8)]  # the last overlaps the first, other class
    out = _yolo_tensor(boxes, scores)
    b, s, c = decode_yolo(out, 0.25, 0.5, 100)
    assert len(s) == 3
    assert np.allclose(b[0], [80, 90, 120, 110]) and s[0] == pytest.approx(0.9) and c[0] == 0
    assert set(zip(c.tolist(), np.round(s.astype(float), 2).tolist())) == {(0, 0.9), (1, 0.8), (1, 0.6)}
    # the transposed layout (1, N, 4 + nc) decodes the same
    b2, s2, c2 = decode_yolo(np.transpose(out, (0, 2, 1)), 0.25, 0.5, 100)
    assert np.allclose(b, b2) and np.allclose(s, s2) and np.array_equal(c, c2)


def test_nms_and_iou():
    b = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30]], float)
    assert np.allclose(iou_matrix(b[:1], b[1:2]), 81 / 119)
    assert list(nms(b, np.array([0.5, 0.9, 0.3]), 0.5)) == [1, 2]
    assert list(nms(b, np.array([0.5, 0.9, 0.3]), 0.5, class_id=np.array([0, 1, 0]))) == [1, 0, 2]


@pytest.mark.parametrize("stride", [STRIDE, 2])
def test_targets_decode_round_trip(stride):
    boxes = np.array([[10.0, 20.0, 17.0, 26.0], [100.3, 40.6, 140.9, 61.2], [200, 200, 204, 204]], np.float32)
    t = make_targets(boxes, np.zeros((0, 4)), 256, 256, stride)
    out = np.concatenate([t["heat"][None], t["reg"]])[None]  # a perfect network's output
    b, s = decode_centernet(out, stride, 0.5, 100)
    assert len(b) == 3 and np.allclose(s, 1.0)
    assert np.allclose(np.sort(b, axis=0), np.sort(boxes, axis=0), atol=1e-3)
    # a heat peak one cell off still decodes to the box (neighbours regress it too)
    box = boxes[1]
    i, j = int(0.5 * (box[1] + box[3]) / stride), int(0.5 * (box[0] + box[2]) / stride)
    shifted = out.copy()
    shifted[0, 0, i, j] = 0.5
    shifted[0, 0, i, j + 1] = 0.9
    b2, s2 = decode_centernet(shifted, stride, 0.6, 100)
    assert np.allclose(b2[np.isclose(s2, 0.9)], box, atol=1e-3)
    # ignore boxes zero the loss weight
    t2 = make_targets(boxes[:1], np.array([[64, 64, 96, 96]]), 256, 256)
    assert t2["weight"][16:24, 16:24].max() == 0 and t2["weight"][0, 0] == 1


def test_tile_starts_cover_with_overlap():
    for n, tile, ov in [(640, 640, 64), (1000, 640, 64), (3000, 640, 100)]:
        s = _tile_starts(n, tile, ov)
        assert s[0] == 0 and s[-1] + tile == max(n, tile)
        assert all(b - a <= tile - ov for a, b in zip(s, s[1:]))


def _save(model, path) -> str:
    onnx.save(model, str(path))
    return str(path)


def _yolo_model(tmp_path, out_const: np.ndarray, in_shape=(1, 3, 64, 64)) -> str:
    """An ONNX model with YOLO output layout: output = constant + 0 * sum(input)."""
    inp = helper.make_tensor_value_info("images", TensorProto.FLOAT, list(in_shape))
    out = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out_const.shape))
    const = numpy_helper.from_array(out_const.astype(np.float32), "const")
    zero = numpy_helper.from_array(np.zeros((), np.float32), "zero")
    nodes = [helper.make_node("ReduceSum", ["images"], ["s"], keepdims=0),
             helper.make_node("Mul", ["s", "zero"], ["z"]),
             helper.make_node("Add", ["const", "z"], ["output0"])]
    graph = helper.make_graph(nodes, "yolo_stub", [inp], [out], initializer=[const, zero])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return _save(model, tmp_path / "yolo_stub.onnx")


def test_yolo_model_letterbox_maps_boxes_back(tmp_path):
    # input 64 x 64; a 128 x 64 (w x h) image is scaled by 0.5 and padded 16 rows above and below
    out = _yolo_tensor([(32, 32, 10, 8)], [(0, 0.9)], nc=1, n_anchor=20)
    path = _yolo_model(tmp_path, out)
    det = RockDetector(path, kind="rover")
    assert det.layout == "yolo" and det.input_size_wh == (64, 64) and det.channels == 3
    d = det.detect(np.zeros((64, 128), np.uint8))
    assert isinstance(d, Detections) and len(d) == 1
    assert np.allclose(d.boxes_xyxy[0], [54, 24, 74, 40], atol=1e-4)  # ((32 -+ 5), (32 -+ 4) - 16) / 0.5
    assert d.score[0] == pytest.approx(0.9)
    # nadir kind tiles at native resolution instead: each 64 x 64 tile reports one box at its
    # centre, which lies in that tile's core, so the image gets one box per tile and no duplicate
    dn = RockDetector(path, kind="nadir").detect(np.zeros((100, 150, 3), np.uint8))
    xs, ys = _tile_starts(150, 64, 16), _tile_starts(100, 64, 16)
    expect = sorted((x + 32.0, y + 32.0) for x in xs for y in ys)
    assert len(dn) == len(expect) == 6
    assert np.allclose(sorted(map(tuple, dn.centers_px)), expect)


def test_bad_model_files_are_rejected(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(DetectorError, match="not a loadable ONNX model"):
        RockDetector(garbage)
    with pytest.raises(DetectorError, match="file not found"):
        RockDetector(tmp_path / "missing.onnx")
    out = _yolo_tensor([(32, 32, 10, 8)], [(0, 0.9)], nc=1, n_anchor=20)
    rank3 = _yolo_model(tmp_path, out, in_shape=(1, 64, 64))
    with pytest.raises(DetectorError, match="N x C x H x W"):
        RockDetector(rank3)
    four_ch = _yolo_model(tmp_path, out, in_shape=(1, 4, 64, 64))
    with pytest.raises(DetectorError, match="4 channels"):
        RockDetector(four_ch)
    no_scores = _yolo_model(tmp_path, np.zeros((1, 4, 20), np.float32))
    with pytest.raises(DetectorError, match="no class scores"):
        RockDetector(no_scores)
    with pytest.raises(DetectorError, match="kind"):
        RockDetector(rank3, kind="orbital")
    assert issubclass(DetectorError, RelocError)


def test_bad_images_are_rejected(tmp_path):
    out = _yolo_tensor([(32, 32, 10, 8)], [(0, 0.9)], nc=1, n_anchor=20)
    det = RockDetector(_yolo_model(tmp_path, out), kind="rover", config=DetectorConfig(score_threshold=0.5))
    with pytest.raises(DetectorError, match="uint8"):
        det.detect(np.zeros((64, 64), np.float32))
    with pytest.raises(DetectorError, match="shape"):
        det.detect(np.zeros((64, 64, 5), np.uint8))

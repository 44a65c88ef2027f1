"""The training script end to end (render, train a few steps, export, calibrate, load with the
runtime). Opt-in: it needs the ``train`` extra (PyTorch, onnx) and is kept out of the default
run; enable with ``FGSLAM_TRAIN_TESTS=1``."""

from __future__ import annotations

import os

import numpy as np
import pytest

if os.environ.get("FGSLAM_TRAIN_TESTS") != "1":
    pytest.skip("training test is opt-in: set FGSLAM_TRAIN_TESTS=1 (needs the train extra)", allow_module_level=True)
pytest.importorskip("torch")
pytest.importorskip("onnx")


@pytest.mark.parametrize("kind", ["nadir", "rover"])
def test_train_export_and_load(tmp_path, kind):
    from fgslam.train.detector import main
    from reloc.detector import RockDetector

    out = tmp_path / f"{kind}.onnx"
    cache = tmp_path / f"{kind}.npz"
    args = ["--kind", kind, "--images", "2", "--iters", "3", "--batch", "2", "--crop", "64",
            "--val-images", "1", "--cache", str(cache), "--out", str(out)]
    assert main(args) == 0
    assert cache.is_file() and out.stat().st_size < 10e6
    det = RockDetector(out, kind=kind)
    assert det.layout == "centernet-v1"
    assert det.input_size_wh == ((640, 640) if kind == "nadir" else (640, 368))
    d = det.detect(np.full((200, 300), 128, np.uint8))
    assert d.boxes_xyxy.shape[1] == 4
    # a second run reads the cached images instead of rendering again
    assert main(args[:-2] + ["--out", str(tmp_path / "again.onnx")]) == 0

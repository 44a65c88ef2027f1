"""The onnxruntime side shared by every detector: open a model file, check its image input, run it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reloc.detector.errors import DetectorError


def open_session(path: Path, threads: int):
    """(onnxruntime session on the CPU with ``threads`` intra-op threads, custom metadata dict) of
    the model at ``path``; a missing or unloadable file raises :class:`DetectorError`."""
    if not path.is_file():
        raise DetectorError(f"detector model {path}: file not found")
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(int(threads), 1)
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        raise DetectorError(f"detector model {path}: not a loadable ONNX model ({exc})") from exc
    return session, dict(session.get_modelmeta().custom_metadata_map)


def image_input(session, path: Path) -> tuple[str, int, list]:
    """(name, channels, shape) of the model's one N x C x H x W float input, C 1 or 3."""
    ins = session.get_inputs()
    if len(ins) != 1:
        raise DetectorError(f"detector model {path}: expected 1 input, found {len(ins)}")
    shape = ins[0].shape
    if len(shape) != 4:
        raise DetectorError(f"detector model {path}: input {ins[0].name!r} has shape {shape}, expected N x C x H x W")
    if shape[1] not in (1, 3):
        raise DetectorError(f"detector model {path}: input has {shape[1]} channels, expected 1 (grey) or 3 (RGB)")
    if "float" not in ins[0].type:
        raise DetectorError(f"detector model {path}: input type {ins[0].type}, expected a float tensor")
    return ins[0].name, int(shape[1]), list(shape)


def run_session(session, path: Path, input_name: str, x: np.ndarray) -> np.ndarray:
    """The model's first output for the input batch ``x``."""
    try:
        return session.run(None, {input_name: x})[0]
    except Exception as exc:
        raise DetectorError(f"detector model {path}: inference failed on input {x.shape} ({exc})") from exc

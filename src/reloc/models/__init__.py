"""Shipped ONNX rock detectors: ``rocks_nadir.onnx`` and ``rocks_rover.onnx`` (see docs/detectors.md)."""

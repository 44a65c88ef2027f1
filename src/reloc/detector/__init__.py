"""Orbital and rover detectors: onnxruntime inference of the shipped rock models (nadir, rover), a
user's Ultralytics YOLO export, and the orbital crater model, with pre-processing (tiling,
letterbox, image pyramid, any bit depth) and decoding.

``RockDetector(kind="nadir").detect(image)`` -> :class:`Detections` (boxes in image pixels);
``CraterDetector().detect(image)`` -> :class:`CraterDetections` (centres, rim diameters);
``orbital_detector(landmark)`` picks the orbital detector of a landmark kind (``registry``).
onnxruntime is imported when a detector is built, so importing this package stays light.
"""

from reloc.detector.boxes import Detections, iou_matrix, nms
from reloc.detector.catalog import catalog_from_detections
from reloc.detector.circles import CraterDetections, circle_iou_matrix, circle_nms
from reloc.detector.craters import CraterConfig, CraterDetector, default_crater_model_path
from reloc.detector.decode import decode_centernet, decode_craters, decode_yolo
from reloc.detector.errors import DetectorError, ImageError
from reloc.detector.registry import orbital_detector, orbital_landmarks, register_orbital_detector
from reloc.detector.runtime import DetectorConfig, RockDetector, default_model_path

__all__ = [
    "CraterConfig",
    "CraterDetections",
    "CraterDetector",
    "Detections",
    "DetectorConfig",
    "DetectorError",
    "ImageError",
    "RockDetector",
    "catalog_from_detections",
    "circle_iou_matrix",
    "circle_nms",
    "decode_centernet",
    "decode_craters",
    "decode_yolo",
    "default_crater_model_path",
    "default_model_path",
    "iou_matrix",
    "nms",
    "orbital_detector",
    "orbital_landmarks",
    "register_orbital_detector",
]

"""Rock detectors: onnxruntime inference of the shipped nadir/rover models or a user's Ultralytics
YOLO export, with pre-processing (tiling, letterbox) and decoding.

``RockDetector(kind="nadir").detect(image)`` -> :class:`Detections` (boxes in image pixels).
onnxruntime is imported when a detector is built, so importing this package stays light.
"""

from reloc.detector.boxes import Detections, iou_matrix, nms
from reloc.detector.catalog import catalog_from_detections
from reloc.detector.decode import decode_centernet, decode_yolo
from reloc.detector.runtime import DetectorConfig, DetectorError, RockDetector, default_model_path

__all__ = [
    "DetectorConfig", "DetectorError", "Detections", "RockDetector", "catalog_from_detections",
    "decode_centernet", "decode_yolo",
    "default_model_path", "iou_matrix", "nms",
]

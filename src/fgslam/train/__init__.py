"""Training of the rock detectors (needs the optional ``train`` extra: PyTorch and onnx).

``python -m fgslam.train --kind nadir --out src/reloc/models/rocks_nadir.onnx`` renders a data
set of procedurally varied worlds, trains the small CenterNet-style detector and exports it.
"""

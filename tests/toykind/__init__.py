"""A toy landmark kind, "cairns", that proves the plug-in seam: one module per layer below, and
the registration (:data:`CAIRNS`); nothing of fgslam is edited for it.

A cairn is a stone marker seen by the stereo front-end as a centre (base_link) with a 3x3
covariance and a height; the orbital catalog lists the cairns' (x, y) and heights.

| layer | module |
| --- | --- |
| measurement, bag | :mod:`tests.toykind.measurement`, :mod:`tests.toykind.bag` |
| EKF update and replay | :mod:`tests.toykind.ekf_update` |
| smoother factors, key symbol ``k``, marginalization | :mod:`tests.toykind.smoother_layer` |
| relocalizer, catalog | :mod:`tests.toykind.relocalizer` |
| rerun | :mod:`tests.toykind.rerun_layer` |
"""

from __future__ import annotations

from reloc.kinds import LandmarkKind

CAIRNS = LandmarkKind(
    name="cairns", measurement="tests.toykind.measurement:CairnObservations", rank=6, symbol="k",
    bag="tests.toykind.bag:CAIRN_CODEC", ekf="tests.toykind.ekf_update:CairnUpdate",
    smoother="tests.toykind.smoother_layer:CairnLandmarks", relocalizer="tests.toykind.relocalizer:CairnRelocalizer",
    catalog="tests.toykind.relocalizer:CAIRN_CATALOG_FILE", rerun="tests.toykind.rerun_layer:CairnLogger",
)

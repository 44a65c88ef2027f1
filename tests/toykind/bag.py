"""Cairns in a bag (toy kind): ``vision_msgs/Detection3DArray`` on ``/cairns``, one Detection3D per
cairn (centre, height as the bbox's z size, covariance in the hypothesis of class ``cairn``)."""

from __future__ import annotations

import numpy as np

from reloc.bag_spec import ROCKS_TYPE, BagCodec, MessageContentError, UnknownFrameError, stamp_s
from tests.toykind.measurement import CairnObservations

CLASS_ID = "cairn"


def encode(m: CairnObservations, ns: int, b):
    T = b.types
    identity = (0.0, 0.0, 0.0, 1.0)
    dets = []
    for i in range(len(m)):
        cov6 = np.eye(6) * b.enc.rock_rotation_var
        cov6[:3, :3] = m.cov_base_m2[i]
        hyp = T["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=CLASS_ID, score=1.0),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=b.pose(m.xyz_base_m[i], identity), covariance=cov6.ravel()))
        bbox = T["vision_msgs/msg/BoundingBox3D"](center=b.pose(m.xyz_base_m[i], identity),
                                                  size=b.vec3((0.3, 0.3, float(m.size_m[i]))))
        dets.append(T["vision_msgs/msg/Detection3D"](header=b.header(ns, b.frame_base), results=[hyp], bbox=bbox,
                                                      id=""))
    return T[ROCKS_TYPE](header=b.header(ns, b.frame_base), detections=dets)


class CairnDecoder:
    def __init__(self, ctx) -> None:
        self.base = ctx.config.base_frame

    def __call__(self, msg, ns: int) -> CairnObservations:
        xyz, cov, size = [], [], []
        for det in msg.detections:
            frame = det.header.frame_id or msg.header.frame_id or self.base
            if frame != self.base:
                raise UnknownFrameError(f"cairns in frame {frame!r}; only {self.base!r} is known")
            c = det.bbox.center.position
            xyz.append((c.x, c.y, c.z))
            size.append(det.bbox.size.z)
            if not det.results:
                raise MessageContentError("a cairn detection without its hypothesis (no covariance)")
            cov.append(np.reshape(det.results[0].pose.covariance, (6, 6))[:3, :3])
        return CairnObservations(stamp_s(ns), np.reshape(xyz, (-1, 3)), np.reshape(cov, (-1, 3, 3)), np.array(size))


CAIRN_CODEC = BagCodec(msgtypes=(ROCKS_TYPE,), default_topic="/cairns", decoder=CairnDecoder, encode=encode)

"""Craters in a bag (the crater kind's bag layer): ``vision_msgs/Detection3DArray`` on
``/craters`` <-> :class:`reloc.craters.CraterObservations`.

A frame is one Detection3DArray; each crater rim one Detection3D:

- ``bbox.center.position``: the rim centre; ``bbox.size``: (D, D, 0), D the rim diameter (m);
- ``results[0]``, class id ``crater``: the detector score and the 6x6 pose covariance whose
  position block is the rim centre's 3x3 covariance (the rotation block says "unknown": a rim
  centre has no orientation);
- ``results[1]``, class id ``crater_rim`` (optional): its score is the fraction of the rim seen
  (completeness, (0, 1]) and its ``pose.covariance[0]`` the variance of the diameter (m^2).
  Without it a crater counts as whole, with a diameter sigma of :data:`DEFAULT_DIAMETER_SIGMA_REL`
  times D.

Detections may be in base_link or in any frame with a known transform to it.
"""

from __future__ import annotations

import numpy as np

from reloc.bag_spec import (
    ROCKS_TYPE,
    BagCodec,
    DecodeContext,
    MessageBuilder,
    MessageContentError,
    UnknownFrameError,
    stamp_s,
)
from reloc.craters import CraterObservations
from reloc.detections import DETECTIONS_PARSER, Detections

CRATER_CLASS_ID = "crater"
RIM_CLASS_ID = "crater_rim"
DEFAULT_DIAMETER_SIGMA_REL = 0.1  # diameter sigma / D of a crater sent without its rim hypothesis


class CraterDecoder:
    """Detection3DArray -> CraterObservations in base_link (see module doc); takes the message
    deserialized or as :class:`reloc.detections.Detections` (straight from its bytes)."""

    def __init__(self, ctx: DecodeContext) -> None:
        self.base = ctx.config.base_frame
        self.T_base_frame = dict(ctx.T_base_frame)

    def __call__(self, msg, ns: int) -> CraterObservations:
        d = msg if isinstance(msg, Detections) else Detections.from_message(msg)
        by_det: list[dict[str, int]] = [{} for _ in range(len(d))]
        for j, (i, c) in enumerate(zip(d.result_det.tolist(), d.class_id, strict=True)):
            by_det[i][c] = j  # the last hypothesis of a class counts
        rows = []
        for i, by_class in enumerate(by_det):
            crater = by_class.get(CRATER_CLASS_ID)
            if crater is None:
                continue  # another class on the crater topic
            frame = d.det_frame[i] or d.frame_id or self.base
            T = self.T_base_frame.get(frame)
            if T is None:
                raise UnknownFrameError(f"crater detections in frame {frame!r}, which has no transform to {self.base!r}")
            c, b = d.center[i, :3], d.size[i]
            diameter = float(max(b[0], b[1]))
            cov6 = d.covariance[crater].reshape(6, 6)
            cov = T[:3, :3] @ cov6[:3, :3] @ T[:3, :3].T
            if not (np.all(np.isfinite(cov)) and np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov)[0] > 0):
                raise MessageContentError("a crater detection without a positive-definite centre covariance")
            rim = by_class.get(RIM_CLASS_ID)
            if rim is None:
                completeness, sigma_d = 1.0, DEFAULT_DIAMETER_SIGMA_REL * diameter
            else:
                completeness = float(d.score[rim])
                var_d = float(d.covariance[rim, 0])
                if not var_d > 0:
                    raise MessageContentError(f"crater rim hypothesis with diameter variance {var_d}")
                sigma_d = float(np.sqrt(var_d))
            rows.append((T[:3, :3] @ c + T[:3, 3], cov, diameter, sigma_d, completeness, float(d.score[crater])))
        n = len(rows)
        return CraterObservations(
            stamp_s(ns), np.reshape([r[0] for r in rows], (n, 3)), np.reshape([r[1] for r in rows], (n, 3, 3)),
            np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), np.array([r[4] for r in rows]),
            np.array([r[5] for r in rows]))


def encode_craters(m: CraterObservations, ns: int, b: MessageBuilder):
    """CraterObservations -> Detection3DArray in ``b.frame_base`` (see module doc)."""
    T = b.types
    identity = (0.0, 0.0, 0.0, 1.0)
    hyp, ohyp, pwc = (T["vision_msgs/msg/ObjectHypothesisWithPose"], T["vision_msgs/msg/ObjectHypothesis"],
                      T["geometry_msgs/msg/PoseWithCovariance"])
    detections = []
    for i in range(len(m)):
        cov6 = np.zeros((6, 6))
        cov6[:3, :3] = m.cov_base_m2[i]
        cov6[3:, 3:] = np.eye(3) * b.enc.rock_rotation_var
        centre = m.xyz_base_m[i]
        d = float(m.size_m[i])
        crater = hyp(hypothesis=ohyp(class_id=CRATER_CLASS_ID, score=float(m.score[i])),
                     pose=pwc(pose=b.pose(centre, identity), covariance=cov6.ravel()))
        cov_d = np.zeros(36)
        cov_d[0] = float(m.size_sigma_m[i]) ** 2
        rim = hyp(hypothesis=ohyp(class_id=RIM_CLASS_ID, score=float(m.completeness[i])),
                  pose=pwc(pose=b.pose((d, 0.0, 0.0), identity), covariance=cov_d))
        bbox = T["vision_msgs/msg/BoundingBox3D"](center=b.pose(centre, identity), size=b.vec3((d, d, 0.0)))
        detections.append(T["vision_msgs/msg/Detection3D"](header=b.header(ns, b.frame_base), results=[crater, rim],
                                                            bbox=bbox, id=""))
    return T[ROCKS_TYPE](header=b.header(ns, b.frame_base), detections=detections)


CRATER_CODEC = BagCodec(msgtypes=(ROCKS_TYPE,), default_topic="/craters", decoder=CraterDecoder, encode=encode_craters,
                        parser=DETECTIONS_PARSER)

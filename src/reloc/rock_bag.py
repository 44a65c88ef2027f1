"""Rocks in a bag (the rock kind's bag layer): ``vision_msgs/Detection3DArray`` <-> RockObservations.

A frame is one Detection3DArray; each rock one Detection3D with the rock centre as
``bbox.center.position``, its diameter as a cubic ``bbox.size``, and one hypothesis (class id
``rock``) carrying the detector score and the 6x6 pose covariance whose position block is the
rock's 3x3 covariance (the rotation block says "unknown": a rock centre has no orientation).
Detections may be in base_link or in any frame with a known transform to it.
"""

from __future__ import annotations

import numpy as np

from reloc.bag_spec import (
    ROCK_CLASS_ID,
    ROCKS_TYPE,
    BagCodec,
    DecodeContext,
    MessageBuilder,
    MessageContentError,
    UnknownFrameError,
    stamp_s,
)
from reloc.detections import DETECTIONS_PARSER, Detections
from reloc.measurements import RockObservations


class RockDecoder:
    """Detection3DArray -> RockObservations in base_link (see module doc); takes the message
    deserialized or as :class:`reloc.detections.Detections` (straight from its bytes).

    Reader settings used (``ctx.config``): ``base_frame``; ``default_rock_sigma_m``, the
    isotropic 1-sigma for detections without a usable covariance (None: such a detection makes
    the message invalid); ``rock_class_ids``, the hypotheses counted as rocks (None: any class;
    the best-scoring hypothesis gives the score and the covariance, the first of equal ones)."""

    def __init__(self, ctx: DecodeContext) -> None:
        self.config = ctx.config
        self.T_base_frame = dict(ctx.T_base_frame)

    def _best(self, d: Detections) -> list[int]:
        """Per detection, the index of its best-scoring rock hypothesis, or -1."""
        ids = self.config.rock_class_ids
        best = [-1] * len(d)
        score = d.score.tolist()
        for j, (i, c) in enumerate(zip(d.result_det.tolist(), d.class_id, strict=True)):
            if ids is None or c in ids:
                b = best[i]
                if b < 0 or score[j] > score[b]:  # as max(): the first of equal (or NaN) scores stays
                    best[i] = j
        return best

    def _covs(self, cov6: np.ndarray, has_cov: np.ndarray) -> np.ndarray:
        """(N, 3, 3) position covariances from (N, 6, 6) pose covariances, or the default."""
        cov = cov6[:, :3, :3].copy()
        finite = np.all(np.isfinite(cov), axis=(1, 2))
        usable = has_cov & finite
        if np.any(usable):
            c = cov[usable]
            sym = np.all(np.abs(c - np.swapaxes(c, 1, 2)) <= 1e-12 * (1.0 + np.abs(c)), axis=(1, 2))
            pd = np.zeros(len(c), dtype=bool)
            pd[sym] = np.linalg.eigvalsh(c[sym])[:, 0] > 0.0
            usable[np.flatnonzero(usable)[~pd]] = False
        bad = ~usable & finite  # NaN covariances stay: RockObservations reports them as NaN
        if np.any(bad):
            if self.config.default_rock_sigma_m is None:
                raise MessageContentError(
                    f"{int(bad.sum())} detection(s) have no positive-definite position "
                    "covariance (set BagReaderConfig.default_rock_sigma_m to supply one)"
                )
            cov[bad] = np.eye(3) * self.config.default_rock_sigma_m**2
        return cov

    def _transforms(self, d: Detections, keep: np.ndarray) -> np.ndarray:
        """(N, 3, 4) [R | t] base_link <- each kept detection's frame."""
        base = self.config.base_frame
        R_t = np.empty((int(keep.sum()), 3, 4))
        for row, i in enumerate(np.flatnonzero(keep).tolist()):
            frame = d.det_frame[i] or d.frame_id or base
            T = self.T_base_frame.get(frame)
            if T is None:
                raise UnknownFrameError(
                    f"rock detections in frame {frame!r}, which has no transform to "
                    f"{base!r}; pass camera_frames={{{frame!r}: T_base_{frame}}}"
                )
            R_t[row] = T[:3]
        return R_t

    def __call__(self, msg, ns: int) -> RockObservations:
        """Decode one frame (detections holding only non-rock classes are skipped)."""
        d = msg if isinstance(msg, Detections) else Detections.from_message(msg)
        n = len(d)
        best = np.array(self._best(d), dtype=np.int64)
        has_results = np.bincount(d.result_det, minlength=n)[:n] > 0
        keep = (best >= 0) | ~has_results  # a detection of other classes only is skipped
        best = best[keep]
        has_cov = best >= 0
        rows = best[has_cov]
        cov6 = np.zeros((len(best), 6, 6))
        cov6[has_cov] = d.covariance[rows].reshape(-1, 6, 6)
        score = np.ones(len(best))
        score[has_cov] = d.score[rows]
        R_t = self._transforms(d, keep)
        xyz = d.center[keep, :3]
        size = d.size[keep].max(axis=1)
        R, t = R_t[:, :, :3], R_t[:, :, 3]
        cov = self._covs(cov6, has_cov)
        return RockObservations(
            stamp_s(ns),
            np.einsum("nij,nj->ni", R, xyz) + t,
            R @ cov @ np.swapaxes(R, 1, 2),
            size,
            score,
        )


def encode_rocks(m: RockObservations, ns: int, b: MessageBuilder):
    """RockObservations -> Detection3DArray in ``b.frame_base`` (see module doc)."""
    T = b.types
    identity = (0.0, 0.0, 0.0, 1.0)
    detections = []
    for i in range(len(m)):
        cov6 = np.zeros((6, 6))
        cov6[:3, :3] = m.cov_base_m2[i]
        cov6[3:, 3:] = np.eye(3) * b.enc.rock_rotation_var
        centre = m.xyz_base_m[i]
        d = float(m.size_m[i])
        result = T["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=ROCK_CLASS_ID, score=float(m.score[i])),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=b.pose(centre, identity), covariance=cov6.ravel()),
        )
        bbox = T["vision_msgs/msg/BoundingBox3D"](center=b.pose(centre, identity), size=b.vec3((d, d, d)))
        detections.append(
            T["vision_msgs/msg/Detection3D"](header=b.header(ns, b.frame_base), results=[result], bbox=bbox, id="")
        )
    return T[ROCKS_TYPE](header=b.header(ns, b.frame_base), detections=detections)


ROCK_CODEC = BagCodec(msgtypes=(ROCKS_TYPE,), default_topic="/rocks", decoder=RockDecoder, encode=encode_rocks,
                      parser=DETECTIONS_PARSER)

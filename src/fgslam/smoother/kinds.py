"""The smoother's side of the landmark-kind seam: variable types by key symbol, what a kind's
smoother layer provides, and the dispatch.

Keys are ``gtsam.Symbol(c, i)``: ``x`` keyframe poses (Pose3), ``c`` the stereo calibration
(Vector4), ``g`` the wheels' slip and ``b`` the IMU's yaw-rate bias from each keyframe on (doubles, when
estimated), ``o`` the fix sources' offsets (Vector3, ``FixConfig.correlation_model`` "bias"),
and each landmark kind's own symbol (``LandmarkKind.symbol``, rocks ``l``) with the
variable type its layer declares. A kind's smoother layer (``LandmarkKind.smoother``) is a class
built as ``cls(config, kind, calib_key)`` (``calib_key`` None without the calibration variable):

- ``variable``: the :class:`VariableType` of its landmarks;
- ``observe(obs, frame)``: associate one frame on the current keyframe (:class:`KeyframeFrame`)
  and buffer its factors and new values into ``frame.graph`` / ``frame.values`` (they enter the
  graph with the next keyframe's update); returns a :class:`reloc.backend.LandmarkUpdateReport`;
- ``buffered_stamps(t)``: the keys it buffered since the last keyframe, stamped ``t`` (fixed lag);
- ``on_keyframe()``: the keyframe update is done (buffers cleared);
- ``drop(index)``: a buffered landmark's update failed, forget it;
- ``marginalize(index, solver)``: the landmark leaves the fixed-lag window: freeze its estimate;
- ``prune(t, oldest_kf)``: drop candidates that timed out or rest on marginalized keyframes;
- ``refresh(T_world_kf, solver)``: after an update, pull the solver's estimates it caches;
- ``landmark_map(pose_cov_at)``: the kind's map in the world (:class:`reloc.backend.LandmarkMap`);
  ``pose_cov_at(t)`` (K,) -> (K, 3, 3) is the rover's position covariance at those times, to add
  to covariances relative to the map;
- ``n_landmarks``, ``n_frames`` (frames used), ``stats()`` (dict of counters);
- optionally ``config_class``, built from ``SmootherConfig.kinds[name]`` (:func:`kind_config`);
- optionally ``anchor_key(lid, solver)`` (the landmark's key while it is a variable of the solver,
  else None) and ``anchored`` (dict: landmark id -> catalog entry, reported in its map's
  ``catalog_row``): the kind's landmarks take catalog anchors (``FixConfig.anchors``).

The smoother keeps them in a :class:`SmootherKinds` (a :class:`reloc.kind_layers.KindLayers`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from fgslam.errors import SmootherError
from reloc.kind_layers import KindLayers, config_with_kinds, layer_config
from reloc.kinds import KindLayerError, LandmarkKind, UnknownKindError, kind_of_symbol

POSE_SYMBOL, CALIB_SYMBOL, SLIP_SYMBOL, YAW_BIAS_SYMBOL, OFFSET_SYMBOL = "x", "c", "g", "b", "o"


@dataclass(frozen=True)
class VariableType:
    """How the solver reads one type of variable: tangent ``dim``, its value in ``gtsam.Values``,
    its estimate from an ISAM2 / fixed-lag smoother, and that value as an array."""

    name: str
    dim: int
    value: Callable[[gtsam.Values, int], Any]
    estimate: Callable[[Any, int], Any]
    as_array: Callable[[Any], np.ndarray]


POSE3 = VariableType("Pose3", 6, lambda v, k: v.atPose3(k), lambda s, k: s.calculateEstimatePose3(k),
                     lambda x: x.matrix())
POINT3 = VariableType("Point3", 3, lambda v, k: v.atPoint3(k), lambda s, k: s.calculateEstimatePoint3(k),
                      lambda x: np.asarray(x, dtype=float))
SCALAR = VariableType("double", 1, lambda v, k: v.atDouble(k), lambda s, k: s.calculateEstimateDouble(k),
                    lambda x: np.atleast_1d(np.asarray(x, dtype=float)))
CALIBRATION = VariableType("Vector4", 4, lambda v, k: v.atVector(k), lambda s, k: s.calculateEstimateVector(k),
                           lambda x: np.asarray(x, dtype=float))
OFFSET = VariableType("Vector3", 3, lambda v, k: v.atVector(k), lambda s, k: s.calculateEstimateVector(k),
                      lambda x: np.asarray(x, dtype=float))


_INDEX_BITS = 56  # gtsam.Symbol: the character in the key's top 8 bits, the index below


def symbol_of(key: int) -> str:
    """The key's character (``x``, ``c``, a kind's symbol); ``gtsam.Symbol(key).chr()`` without
    building a Symbol (this runs for every variable the solver reads)."""
    return chr(key >> _INDEX_BITS)


def variable_type(symbol: str) -> VariableType:
    """The variable type of keys with character ``symbol``; :class:`SmootherError` when no kind
    uses it."""
    if symbol == POSE_SYMBOL:
        return POSE3
    if symbol == CALIB_SYMBOL:
        return CALIBRATION
    if symbol in (SLIP_SYMBOL, YAW_BIAS_SYMBOL):
        return SCALAR
    if symbol == OFFSET_SYMBOL:
        return OFFSET
    try:
        return kind_of_symbol(symbol).layer("smoother").variable
    except (UnknownKindError, KindLayerError) as exc:
        raise SmootherError(f"key symbol {symbol!r} is no variable of the smoother: {exc}") from None


def kind_config(cls: type, kind: LandmarkKind, config) -> Any:
    """The resolved config of ``kind``'s smoother layer ``cls`` (None when it declares none)."""
    return layer_config(cls, kind, config.kinds, "isam2")


def resolved_smoother_config(config) -> dict:
    """The resolved config as a plain dict, every registered kind's smoother settings in ``kinds``."""
    return config_with_kinds(config, "smoother", "isam2")


@dataclass(frozen=True)
class KeyframeFrame:
    """What a kind's ``observe`` sees: the current keyframe ``kf``, its estimate ``T_world_kf``
    (4, 4), the odometry since it (``T_kf_now`` (4, 4), ``cov_kf_now`` (6, 6) GTSAM body frame),
    and the buffers of the next keyframe update. ``cov_growth(t_last)`` (K,) -> (K, 6, 6): how much
    more uncertain (GTSAM body frame) the current keyframe is than the keyframes at those times, i.e.
    its uncertainty relative to landmarks last seen then (None: none)."""

    kf: int
    T_world_kf: np.ndarray
    T_kf_now: np.ndarray
    cov_kf_now: np.ndarray
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    cov_growth: Callable[[np.ndarray], np.ndarray] | None = None


class SmootherKinds(KindLayers):
    """The smoother's kind layers, each built as ``cls(config, kind, calib_key)`` on first use
    (creation order kept), and found by an observation or by a landmark key."""

    def __init__(self, config, calib_key: int | None) -> None:
        super().__init__("smoother", lambda kind: kind.layer("smoother")(config, kind, calib_key), SmootherError,
                         "smoother", config.kinds)

    def for_key(self, key: int):
        """The layer owning landmark ``key``; :class:`SmootherError` for a symbol of no kind."""
        try:
            kind = kind_of_symbol(symbol_of(key))
        except UnknownKindError as exc:
            raise SmootherError(f"key {gtsam.DefaultKeyFormatter(key)} belongs to no landmark kind: {exc}") from None
        return self.get(kind.name)

"""Typed measurements shared by the simulator, the bag reader and both back-ends.

Frames and units follow DESIGN.md: ``world`` is the orbital map frame (ENU, metres), ``base_link``
is x forward, y left, z up. Times are float seconds. Every constructor validates its input and
raises :class:`~reloc.errors.MeasurementError` naming the field and the problem, so a NaN or a
wrong shape never reaches a filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Union

import numpy as np

from reloc import kinds
from reloc.errors import MeasurementError


def _finite(name: str, value: np.ndarray | float) -> None:
    if not np.all(np.isfinite(value)):
        raise MeasurementError(f"{name} contains NaN or inf: {value!r}")


def _array(name: str, value, shape: tuple[int | None, ...]) -> np.ndarray:
    arr = np.array(value, dtype=float)  # a copy: callers cannot mutate a stored measurement
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise MeasurementError(f"{name} must have shape {shape}, got {arr.shape}")
    _finite(name, arr)
    arr.setflags(write=False)
    return arr


def _time(name: str, t: float) -> float:
    t = float(t)
    if not math.isfinite(t):  # math, not numpy: this runs for every scalar of every message
        raise MeasurementError(f"{name} is NaN or inf: {t!r}")
    return t


def _unit_quat(name: str, q) -> np.ndarray:
    q = _array(name, q, (4,))
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise MeasurementError(f"{name} must be a unit quaternion (x, y, z, w), norm is {n:.6f}")
    q = q / n
    q.setflags(write=False)
    return q


@dataclass(frozen=True, slots=True)
class CmdVel:
    """Commanded body velocity at time ``t``: forward speed (base_link x) and yaw rate (about z)."""

    t: float
    v_mps: float
    yaw_rate_radps: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("CmdVel.t", self.t))
        object.__setattr__(self, "v_mps", _time("CmdVel.v_mps", self.v_mps))
        object.__setattr__(self, "yaw_rate_radps", _time("CmdVel.yaw_rate_radps", self.yaw_rate_radps))


@dataclass(frozen=True, slots=True)
class ImuSample:
    """IMU output at ``t``.

    ``quat_xyzw``: orientation of base_link in the IMU's gravity-aligned reference frame (roll and
    pitch observable, yaw integrated from the gyro and so drifting). ``gyro_radps`` (3,) and
    ``accel_mps2`` (3,) are in base_link (accel is specific force: +9.81 z at rest).
    """

    t: float
    quat_xyzw: np.ndarray
    gyro_radps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_mps2: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 9.81]))

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("ImuSample.t", self.t))
        object.__setattr__(self, "quat_xyzw", _unit_quat("ImuSample.quat_xyzw", self.quat_xyzw))
        object.__setattr__(self, "gyro_radps", _array("ImuSample.gyro_radps", self.gyro_radps, (3,)))
        object.__setattr__(self, "accel_mps2", _array("ImuSample.accel_mps2", self.accel_mps2, (3,)))


@dataclass(frozen=True, slots=True)
class WheelOdometry:
    """Wheel odometry at ``t``: measured forward speed and yaw rate in base_link (optional input)."""

    t: float
    v_mps: float
    yaw_rate_radps: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("WheelOdometry.t", self.t))
        object.__setattr__(self, "v_mps", _time("WheelOdometry.v_mps", self.v_mps))
        object.__setattr__(
            self, "yaw_rate_radps", _time("WheelOdometry.yaw_rate_radps", self.yaw_rate_radps)
        )


@dataclass(frozen=True, slots=True)
class RockObservations:
    """One stereo frame of rock detections at ``t`` (possibly empty, N = 0).

    ``xyz_base_m`` (N, 3): rock centres in base_link; ``cov_base_m2`` (N, 3, 3): their covariance
    in base_link (stereo triangulation: depth variance grows with range squared); ``size_m`` (N,):
    estimated diameter; ``score`` (N,): detector confidence in [0, 1].
    """

    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray
    size_m: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("RockObservations.t", self.t))
        xyz = _array("RockObservations.xyz_base_m", np.reshape(self.xyz_base_m, (-1, 3)), (None, 3))
        n = xyz.shape[0]
        cov = _array("RockObservations.cov_base_m2", np.reshape(self.cov_base_m2, (-1, 3, 3)), (n, 3, 3))
        size = _array("RockObservations.size_m", np.reshape(self.size_m, (-1,)), (n,))
        score = _array("RockObservations.score", np.reshape(self.score, (-1,)), (n,))
        if n and np.any(np.abs(cov - np.swapaxes(cov, 1, 2)) > 1e-9 * (1.0 + np.abs(cov))):
            raise MeasurementError("RockObservations.cov_base_m2 must be symmetric")
        if n and np.any(np.linalg.eigvalsh(cov)[:, 0] <= 0.0):
            raise MeasurementError("RockObservations.cov_base_m2 must be positive definite")
        if np.any(size <= 0.0):
            raise MeasurementError("RockObservations.size_m must be positive")
        for name, value in (("xyz_base_m", xyz), ("cov_base_m2", cov), ("size_m", size), ("score", score)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.xyz_base_m.shape[0])


@dataclass(frozen=True, slots=True)
class GroundTruthPose:
    """True pose of base_link in world at ``t`` (simulator only; always optional downstream)."""

    t: float
    position_m: np.ndarray
    quat_xyzw: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _time("GroundTruthPose.t", self.t))
        object.__setattr__(self, "position_m", _array("GroundTruthPose.position_m", self.position_m, (3,)))
        object.__setattr__(self, "quat_xyzw", _unit_quat("GroundTruthPose.quat_xyzw", self.quat_xyzw))


# A measurement is a motion input, a ground-truth pose, or the observation of a registered
# landmark kind (reloc.kinds): the union names the built-in ones for type checkers.
Measurement = Union[CmdVel, ImuSample, WheelOdometry, RockObservations, GroundTruthPose]

# Order of measurements that share a stamp: motion inputs first, so that a landmark frame at t is
# applied to the state predicted to t; each landmark kind registers its own rank after these.
INPUT_RANK: dict[type, int] = {
    CmdVel: 0,
    WheelOdometry: 1,
    ImuSample: 2,
    GroundTruthPose: 3,
}


def sort_rank(m) -> int:
    """Rank of ``m`` among same-stamp measurements: :data:`INPUT_RANK`, else its kind's rank
    (:class:`reloc.kinds.UnknownKindError` for a type that is neither)."""
    rank = INPUT_RANK.get(type(m))
    return rank if rank is not None else kinds.kind_of(m).rank


def sort_key(m: Measurement) -> tuple[float, int]:
    """Key that orders a stream by time, then by :func:`sort_rank`."""
    rank = INPUT_RANK.get(type(m))
    return (m.t, rank if rank is not None else kinds.kind_of(m).rank)


@dataclass(frozen=True, slots=True)
class FixHeight:
    """The height of base_link at a fix, read from an orbital terrain model at the fix's (x, y):
    ``z_m`` (world), ``var_m2`` its variance (the model's own error and the fix's planar error
    through the terrain's slope), ``cov_xyyaw`` (3,) its covariance with the fix's (x, y, yaw)."""

    z_m: float
    var_m2: float
    cov_xyyaw: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "z_m", _time("FixHeight.z_m", self.z_m))
        object.__setattr__(self, "var_m2", _time("FixHeight.var_m2", self.var_m2))
        if not self.var_m2 > 0.0:
            raise MeasurementError(f"FixHeight.var_m2 must be positive, got {self.var_m2}")
        object.__setattr__(self, "cov_xyyaw", _array("FixHeight.cov_xyyaw", np.reshape(self.cov_xyyaw, -1), (3,)))


@dataclass(frozen=True, slots=True)
class CatalogAnchor:
    """A landmark of a back-end's map identified with an orbital catalog entry: landmark
    ``landmark_id`` of kind ``kind`` (the back-end's id, :class:`reloc.backend.LandmarkMap`) lies
    at the entry's ``xy_m`` (2,, world) with ``cov_xy`` (2, 2): the entry's own error only (the
    rover's error relative to the landmark is the back-end's to know). ``catalog_row``: the entry."""

    kind: str
    landmark_id: int
    catalog_row: int
    xy_m: np.ndarray
    cov_xy: np.ndarray

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or not self.kind:
            raise MeasurementError(f"CatalogAnchor.kind must be a kind's name, got {self.kind!r}")
        object.__setattr__(self, "landmark_id", int(self.landmark_id))
        object.__setattr__(self, "catalog_row", int(self.catalog_row))
        if self.catalog_row < 0:
            raise MeasurementError(f"CatalogAnchor.catalog_row must be >= 0, got {self.catalog_row}")
        object.__setattr__(self, "xy_m", _array("CatalogAnchor.xy_m", np.reshape(self.xy_m, -1), (2,)))
        cov = _array("CatalogAnchor.cov_xy", self.cov_xy, (2, 2))
        if np.any(np.abs(cov - cov.T) > 1e-9 * (1.0 + np.abs(cov))) or np.linalg.eigvalsh(cov)[0] <= 0:
            raise MeasurementError("CatalogAnchor.cov_xy must be symmetric positive definite")
        object.__setattr__(self, "cov_xy", cov)


@dataclass(frozen=True, slots=True)
class GlobalFix:
    """A global pose fix of base_link in world, valid at ``t_meas``, delivered at ``t_recv``:
    planar (x, y, yaw), and with ``height`` (:class:`FixHeight`) also z.

    ``cov_xyyaw`` (3, 3): covariance of (x_m, y_m, yaw_rad). ``n_inliers``/``rmse_m`` describe the
    constellation match that produced it. ``measured`` / ``cov`` are the fix as one vector
    (x, y, yaw[, z]) with its (3, 3) or (4, 4) covariance, the form the back-ends update with.

    Successive fixes from one catalog share its errors. ``source`` names the catalog's landmark
    kind(s); ``correlation_scale`` (>= 1) is the factor the producer multiplied the match's
    covariance by for that (its correlation model), and ``cov_relative_xy`` (2, 2) the rover's
    drift from its map added after it, so ``cov_xyyaw = correlation_scale * C_match + C_rel``: a
    consumer with its own correlation model takes :meth:`recorrelated`. ``catalog_rows``: the
    catalog entries the match used (fixes that share none share no catalog error).

    ``anchors``: where the fix came from landmarks identified one by one with catalog entries
    (:class:`CatalogAnchor`), those identifications. A back-end that holds every anchor's
    landmark as a variable may put the entries on the landmarks instead of the pose (each
    entry's error then counted once, however many later fixes would have repeated it) and
    :meth:`height_only` on the pose; otherwise it takes the fix as a pose. A fix whose pose is
    changed must drop them (``anchors=()``).
    """

    t_meas: float
    t_recv: float
    x_m: float
    y_m: float
    yaw_rad: float
    cov_xyyaw: np.ndarray
    n_inliers: int = 0
    rmse_m: float = 0.0
    height: FixHeight | None = None
    source: str = ""
    correlation_scale: float = 1.0
    cov_relative_xy: np.ndarray | None = None
    catalog_rows: tuple[int, ...] = ()  # the catalog entries the match used (empty: not known)
    anchors: tuple[CatalogAnchor, ...] = ()

    def __post_init__(self) -> None:
        anchors = tuple(self.anchors)
        if not all(isinstance(a, CatalogAnchor) for a in anchors):
            raise MeasurementError("GlobalFix.anchors must hold CatalogAnchor only")
        object.__setattr__(self, "anchors", anchors)
        for name in ("t_meas", "t_recv", "x_m", "y_m", "yaw_rad", "rmse_m"):
            object.__setattr__(self, name, _time(f"GlobalFix.{name}", getattr(self, name)))
        if not isinstance(self.source, str):
            raise MeasurementError(f"GlobalFix.source must be a string, got {type(self.source).__name__}")
        scale = _time("GlobalFix.correlation_scale", self.correlation_scale)
        if not scale >= 1.0:
            raise MeasurementError(f"GlobalFix.correlation_scale must be >= 1, got {scale}")
        object.__setattr__(self, "correlation_scale", scale)
        object.__setattr__(self, "catalog_rows", tuple(sorted({int(r) for r in self.catalog_rows})))
        if self.cov_relative_xy is not None:
            rel = _array("GlobalFix.cov_relative_xy", self.cov_relative_xy, (2, 2))
            if np.any(np.abs(rel - rel.T) > 1e-9 * (1.0 + np.abs(rel))) or np.linalg.eigvalsh(rel)[0] < -1e-12 * (
                    1.0 + np.trace(np.abs(rel))):
                raise MeasurementError("GlobalFix.cov_relative_xy must be symmetric positive semi-definite")
            object.__setattr__(self, "cov_relative_xy", rel)
        if self.t_recv < self.t_meas:
            raise MeasurementError(
                f"GlobalFix.t_recv ({self.t_recv}) is before t_meas ({self.t_meas})"
            )
        cov = _array("GlobalFix.cov_xyyaw", self.cov_xyyaw, (3, 3))
        if np.any(np.abs(cov - cov.T) > 1e-9 * (1.0 + np.abs(cov))) or np.linalg.eigvalsh(cov)[0] <= 0:
            raise MeasurementError("GlobalFix.cov_xyyaw must be symmetric positive definite")
        object.__setattr__(self, "cov_xyyaw", cov)
        object.__setattr__(self, "n_inliers", int(self.n_inliers))
        if self.height is not None:
            if not isinstance(self.height, FixHeight):
                raise MeasurementError(f"GlobalFix.height must be a FixHeight or None, got {type(self.height).__name__}")
            if np.linalg.eigvalsh(self.cov)[0] <= 0:
                raise MeasurementError("GlobalFix.height: the (x, y, yaw, z) covariance is not positive definite")

    @property
    def xyyaw(self) -> np.ndarray:
        """(3,) array (x_m, y_m, yaw_rad)."""
        return np.array([self.x_m, self.y_m, self.yaw_rad])

    @property
    def measured(self) -> np.ndarray:
        """(3,) (x, y, yaw), or (4,) (x, y, yaw, z) with a height."""
        if self.height is None:
            return self.xyyaw
        return np.array([self.x_m, self.y_m, self.yaw_rad, self.height.z_m])

    @property
    def cov(self) -> np.ndarray:
        """Covariance of :attr:`measured`: (3, 3), or (4, 4) with a height."""
        if self.height is None:
            return self.cov_xyyaw.copy()
        C = np.empty((4, 4))
        C[:3, :3] = self.cov_xyyaw
        C[3, :3] = C[:3, 3] = self.height.cov_xyyaw
        C[3, 3] = self.height.var_m2
        return C

    def planar(self) -> GlobalFix:
        """This fix without its height."""
        return self if self.height is None else replace(self, height=None)

    def height_only(self, planar_sigma_m: float = 1.0e3, yaw_sigma_rad: float = 1.0e2) -> GlobalFix | None:
        """The fix's height alone (None without one), as a fix whose (x, y, yaw) say nothing
        (``planar_sigma_m``, ``yaw_sigma_rad``, uncorrelated with z) and whose z keeps its
        variance about the fix's own (x, y), the terrain read there: what a back-end applies
        beside the fix's anchors, which hold its planar part. It names no ``source``: its height is
        the terrain model's, not the catalog's, so it shares no catalog error (a back-end holding
        the source's offset as a state would otherwise take a kilometre of planar variance for it)."""
        if self.height is None:
            return None
        cov = np.diag([planar_sigma_m**2, planar_sigma_m**2, yaw_sigma_rad**2])
        return replace(self, cov_xyyaw=cov, cov_relative_xy=None, correlation_scale=1.0, anchors=(), source="",
                       height=FixHeight(self.height.z_m, self.height.var_m2, np.zeros(3)))

    def split_cov(self) -> tuple[np.ndarray, np.ndarray]:
        """(C_match, C_rel) (3, 3) each: the match's covariance before the producer's correlation
        factor, and the rover-relative part (zero without one)."""
        rel = np.zeros((3, 3))
        if self.cov_relative_xy is not None:
            rel[:2, :2] = self.cov_relative_xy
        match = (self.cov_xyyaw - rel) / self.correlation_scale
        return 0.5 * (match + match.T), rel

    def height_model(self) -> tuple[np.ndarray, float]:
        """(g (3,), var_model) of a height read at the fix's (x, y), ``z = model(x, y)``: its
        covariance with (x, y, yaw) is ``C g`` (``g`` the terrain gradient, recovered from it) and
        its variance ``var_model + g^T C g`` (``var_model`` the terrain model's own)."""
        if self.height is None:
            raise MeasurementError("GlobalFix.height_model: the fix has no height")
        g = np.linalg.solve(self.cov_xyyaw, self.height.cov_xyyaw)
        return g, float(self.height.var_m2 - g @ self.height.cov_xyyaw)

    def recorrelated(self, scale: float) -> GlobalFix:
        """This fix with its match covariance multiplied by ``scale`` (>= 1) instead of its
        producer's ``correlation_scale``; the rover-relative part stays as it is. A height read
        at the fix's (x, y) (``z = model(x, y)``: its covariance with them is ``C g`` for the
        terrain gradient ``g``) follows: its covariance and variance are propagated again."""
        if scale == self.correlation_scale:
            return self
        match, rel = self.split_cov()
        return self._with_planar_cov(scale * match + rel, scale)

    def unshared(self, share: float) -> GlobalFix:
        """This fix less ``share`` (0 < share < 1) of its match covariance (without the producer's
        correlation factor): the part of its error that a back-end holds as its source's shared
        offset instead (the smoother's ``fixes.correlation_model`` "bias", the EKF's
        ``fix_gate.correlation_model`` "bias"). The rover-relative part stays; a height follows as
        in :meth:`recorrelated`."""
        if not 0.0 < share < 1.0:
            raise MeasurementError(f"GlobalFix.unshared: share must be in (0, 1), got {share}")
        match, rel = self.split_cov()
        return self._with_planar_cov((1.0 - share) * match + rel, 1.0)

    def _with_planar_cov(self, cov: np.ndarray, scale: float) -> GlobalFix:
        """This fix with (x, y, yaw) covariance ``cov`` and correlation factor ``scale``; a height
        read at the fix's (x, y) (``z = model(x, y)``: its covariance with them is ``C g`` for the
        terrain gradient ``g``) propagated again."""
        height = self.height
        if height is not None:
            g, var_model = self.height_model()
            cz = cov @ g
            height = FixHeight(height.z_m, var_model + float(g @ cz), cz)
        return replace(self, cov_xyyaw=cov, correlation_scale=scale, height=height)


@dataclass(frozen=True, slots=True)
class RockCatalog:
    """A 2D rock catalog in the world frame (orbital detections): ``xy_m`` (N, 2), ``size_m`` (N,)
    diameters, ``score`` (N,) detector confidences. The CSV form is ``x,y,size,score``."""

    xy_m: np.ndarray
    size_m: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        xy = _array("RockCatalog.xy_m", np.reshape(self.xy_m, (-1, 2)), (None, 2))
        n = xy.shape[0]
        size = _array("RockCatalog.size_m", np.reshape(self.size_m, (-1,)), (n,))
        score = _array("RockCatalog.score", np.reshape(self.score, (-1,)), (n,))
        if np.any(size <= 0.0):
            raise MeasurementError("RockCatalog.size_m must be positive")
        object.__setattr__(self, "xy_m", xy)
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "score", score)

    def __len__(self) -> int:
        return int(self.xy_m.shape[0])


# --- batches ------------------------------------------------------------------------------------
# Readers of long recordings build millions of motion measurements; validating each in its
# constructor costs more than decoding it. These build a batch with the constructors' checks done
# on whole arrays (the same tolerances, the same normalisation to the bit); a row that fails is
# handed to the constructor, so its error is the constructor's own.


def _unchecked(cls, **values):
    obj = object.__new__(cls)
    for name, value in values.items():
        object.__setattr__(obj, name, value)
    return obj


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _row_ok(*arrays: np.ndarray) -> np.ndarray:
    return np.all(np.column_stack([np.isfinite(a).reshape(len(a), -1) for a in arrays]), axis=1)


def _checked(cls, ok: np.ndarray, rows, build) -> list:
    """Per row: ``build(i)`` where ``ok``, else ``cls(*rows(i))`` or the MeasurementError it raises."""
    out = []
    for i, good in enumerate(ok.tolist()):
        if good:
            out.append(build(i))
            continue
        try:
            out.append(cls(*rows(i)))
        except MeasurementError as exc:
            out.append(exc)
    return out


def batch_planar(cls, t: np.ndarray, v_mps: np.ndarray, yaw_rate_radps: np.ndarray) -> list:
    """:class:`CmdVel` or :class:`WheelOdometry` for (K,) stamps, speeds and yaw rates; a row
    that is no valid measurement gives its :class:`MeasurementError` instead."""
    if cls not in (CmdVel, WheelOdometry):
        raise MeasurementError(f"batch_planar builds CmdVel or WheelOdometry, not {cls.__name__}")
    t, v, w = (np.asarray(a, dtype=float) for a in (t, v_mps, yaw_rate_radps))
    tl, vl, wl = t.tolist(), v.tolist(), w.tolist()
    return _checked(cls, _row_ok(t, v, w), lambda i: (tl[i], vl[i], wl[i]),
                    lambda i: _unchecked(cls, t=tl[i], v_mps=vl[i], yaw_rate_radps=wl[i]))


def _unit_rows(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(quat, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return _frozen(quat / n[:, None]), np.abs(n - 1.0) <= 1e-3


def batch_imu(t: np.ndarray, quat_xyzw: np.ndarray, gyro_radps: np.ndarray, accel_mps2: np.ndarray) -> list:
    """:class:`ImuSample` of (K,) stamps, (K, 4) quaternions, (K, 3) rates and (K, 3) specific forces."""
    t = np.asarray(t, dtype=float)
    q_raw, g, a = (np.asarray(x, dtype=float) for x in (quat_xyzw, gyro_radps, accel_mps2))
    q, unit = _unit_rows(q_raw)
    g, a = _frozen(g), _frozen(a)
    tl = t.tolist()
    return _checked(ImuSample, _row_ok(t, q_raw, g, a) & unit, lambda i: (tl[i], q_raw[i], g[i], a[i]),
                    lambda i: _unchecked(ImuSample, t=tl[i], quat_xyzw=q[i], gyro_radps=g[i], accel_mps2=a[i]))


def batch_ground_truth(t: np.ndarray, position_m: np.ndarray, quat_xyzw: np.ndarray) -> list:
    """:class:`GroundTruthPose` of (K,) stamps, (K, 3) positions and (K, 4) quaternions."""
    t = np.asarray(t, dtype=float)
    p, q_raw = _frozen(position_m), np.asarray(quat_xyzw, dtype=float)
    q, unit = _unit_rows(q_raw)
    tl = t.tolist()
    return _checked(GroundTruthPose, _row_ok(t, p, q_raw) & unit, lambda i: (tl[i], p[i], q_raw[i]),
                    lambda i: _unchecked(GroundTruthPose, t=tl[i], position_m=p[i], quat_xyzw=q[i]))

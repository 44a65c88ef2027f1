"""Landmark kinds as plug-ins: the one registry the runner, the back-ends and the bag reader
dispatch on.

A landmark kind (rocks, craters) is one module per layer, named in one
:class:`LandmarkKind` and registered once (:func:`register_kind`); nothing else is edited:

- ``measurement`` (reloc): the observation type (``t``, ``xyz_base_m`` (N, 3), ``cov_base_m2``
  (N, 3, 3), ``size_m`` (N,), ``len``; :class:`LandmarkObservations`);
- ``rank`` (reloc): its order among same-stamp measurements (motion inputs and ground truth take
  0-3, kinds 4 and up);
- ``symbol`` (fgslam.smoother): the GTSAM key character of its landmarks (not x, c);
- ``bag`` (reloc; sim writes, fgslam.io reads): a :class:`reloc.bag_spec.BagCodec`;
- ``ekf`` (ekf): an update class (:class:`ekf.kinds.EkfKindUpdate`): update, history replay, map;
- ``smoother`` (fgslam.smoother): a layer class (see :mod:`fgslam.smoother.kinds`): factors,
  variable type, marginalization, map;
- ``relocalizer`` (fgslam): a factory ``(catalog, config) -> relocalizer``;
- ``catalog`` (fgslam.io): the catalog's file name and reader;
- ``rerun`` (fgslam.viz): a logger of its catalog and maps (default: points and ellipses).

Layers are named as ``"module:attribute"`` strings and imported on first use, so ``reloc``
never imports the packages above it and a run loads only the layers it needs. A kind may leave
a layer out (``None``); asking for it is then a :class:`KindLayerError`, and an observation of
an unregistered type is an :class:`UnknownKindError` wherever it turns up: never taken for a fix
or a rock. Packages outside fgslam register their kinds through the entry-point group
``fgslam.landmark_kinds`` (each entry point names a :class:`LandmarkKind`).
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from reloc.errors import RelocError

ENTRY_POINT_GROUP = "fgslam.landmark_kinds"
FIRST_KIND_RANK = 4  # CmdVel 0, WheelOdometry 1, ImuSample 2, GroundTruthPose 3
# the smoother's own variables: keyframe poses, the stereo calibration, the wheels' slip, the
# yaw-rate bias, the fix sources' offsets (fgslam.smoother.kinds)
RESERVED_SYMBOLS = frozenset("xcgbo")
LAYERS = ("measurement", "bag", "ekf", "smoother", "relocalizer", "catalog", "rerun")


class UnknownKindError(RelocError, KeyError):
    """No landmark kind is registered under that name, measurement type or key symbol."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class KindLayerError(RelocError):
    """A kind is registered but lacks the layer asked for, or that layer does not import."""


@runtime_checkable
class LandmarkObservations(Protocol):
    """What every kind's observation exposes (its point view: rock centres, crater rims, ...)."""

    t: float
    xyz_base_m: np.ndarray  # (N, 3) m in base_link
    cov_base_m2: np.ndarray  # (N, 3, 3) m^2 in base_link
    size_m: np.ndarray  # (N,) m (rock diameter, crater rim diameter)

    def __len__(self) -> int: ...


@dataclass(frozen=True)
class LandmarkKind:
    """One landmark kind: its name, sort rank, key symbol and its layers (``"module:attr"``)."""

    name: str
    measurement: str | type
    rank: int
    symbol: str
    bag: str | None = None
    ekf: str | None = None
    smoother: str | None = None
    relocalizer: str | None = None
    catalog: str | None = None
    rerun: str | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and self.name.isidentifier()):
            raise KindLayerError(f"landmark kind name must be an identifier, got {self.name!r}")
        if not (isinstance(self.rank, int) and self.rank >= FIRST_KIND_RANK):
            raise KindLayerError(f"kind {self.name!r}: rank must be an int >= {FIRST_KIND_RANK}, got {self.rank!r}")
        if not (isinstance(self.symbol, str) and len(self.symbol) == 1 and self.symbol.isalpha()
                and self.symbol.islower() and self.symbol not in RESERVED_SYMBOLS):
            raise KindLayerError(f"kind {self.name!r}: symbol must be one lower-case letter other than "
                                 f"{sorted(RESERVED_SYMBOLS)}, got {self.symbol!r}")

    def has(self, layer: str) -> bool:
        """Whether the kind provides ``layer`` (one of :data:`LAYERS`)."""
        return getattr(self, layer) is not None

    def layer(self, layer: str) -> Any:
        """The object the kind names for ``layer``, imported on first use."""
        if layer not in LAYERS:
            raise KindLayerError(f"unknown layer {layer!r}; layers are {list(LAYERS)}")
        ref = getattr(self, layer)
        if ref is None:
            raise KindLayerError(f"landmark kind {self.name!r} has no {layer} layer")
        if not isinstance(ref, str):
            return ref
        hit = _RESOLVED.get((self.name, layer, ref))
        if hit is None:
            module, _, attr = ref.partition(":")
            try:
                hit = getattr(importlib.import_module(module), attr)
            except (ImportError, AttributeError) as exc:
                raise KindLayerError(f"landmark kind {self.name!r}: {layer} layer {ref!r} does not import: {exc}") from exc
            _RESOLVED[(self.name, layer, ref)] = hit
        return hit

    @property
    def measurement_type(self) -> type:
        return self.layer("measurement")


_KINDS: dict[str, LandmarkKind] = {}
_RESOLVED: dict[tuple[str, str, str], Any] = {}
_BY_TYPE: dict[type, LandmarkKind] | None = None
_BY_SYMBOL: dict[str, LandmarkKind] | None = None
_CODES: dict[str, int] = {}  # stable per process: a kind keeps its code across re-registration
_PLUGINS_LOADED = False


def register_kind(kind: LandmarkKind) -> LandmarkKind:
    """Add ``kind`` to the registry; its name, rank and symbol must be free."""
    global _BY_TYPE, _BY_SYMBOL
    if not isinstance(kind, LandmarkKind):
        raise KindLayerError(f"register_kind takes a LandmarkKind, got {type(kind).__name__}")
    for other in _KINDS.values():
        if other.name == kind.name:
            raise KindLayerError(f"landmark kind {kind.name!r} is already registered")
        if other.rank == kind.rank:
            raise KindLayerError(f"kind {kind.name!r}: rank {kind.rank} is taken by {other.name!r}")
        if other.symbol == kind.symbol:
            raise KindLayerError(f"kind {kind.name!r}: symbol {kind.symbol!r} is taken by {other.name!r}")
    _KINDS[kind.name] = kind
    _CODES.setdefault(kind.name, len(_CODES))
    _BY_TYPE = _BY_SYMBOL = None
    return kind


def unregister_kind(name: str) -> None:
    """Remove kind ``name`` (tests; a run keeps its kinds)."""
    global _BY_TYPE, _BY_SYMBOL
    kind_named(name)
    del _KINDS[name]
    for key in [k for k in _RESOLVED if k[0] == name]:
        del _RESOLVED[key]
    _BY_TYPE = _BY_SYMBOL = None


@contextlib.contextmanager
def registered(kind: LandmarkKind) -> Iterator[LandmarkKind]:
    """``with registered(kind):`` the kind is registered inside the block only."""
    register_kind(kind)
    try:
        yield kind
    finally:
        unregister_kind(kind.name)


def _load_plugins() -> None:
    global _PLUGINS_LOADED
    if _PLUGINS_LOADED:
        return
    _PLUGINS_LOADED = True
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        kind = ep.load()
        if kind.name not in _KINDS:
            register_kind(kind)


def all_kinds() -> tuple[LandmarkKind, ...]:
    """Every registered kind, in registration order."""
    _load_plugins()
    return tuple(_KINDS.values())


def kind_names() -> tuple[str, ...]:
    return tuple(k.name for k in all_kinds())


def kinds_with(layer: str) -> tuple[LandmarkKind, ...]:
    """The registered kinds that provide ``layer``."""
    return tuple(k for k in all_kinds() if k.has(layer))


def kind_named(name: str) -> LandmarkKind:
    """The kind registered as ``name``."""
    _load_plugins()
    kind = _KINDS.get(name)
    if kind is None:
        raise UnknownKindError(f"no landmark kind {name!r} is registered; registered kinds: {list(_KINDS)}")
    return kind


def kind_of(obs_or_type: Any) -> LandmarkKind:
    """The kind of an observation (or of its type); :class:`UnknownKindError` for any other."""
    global _BY_TYPE
    cls = obs_or_type if isinstance(obs_or_type, type) else type(obs_or_type)
    if _BY_TYPE is None:
        _BY_TYPE = {k.measurement_type: k for k in all_kinds()}
    kind = _BY_TYPE.get(cls)
    if kind is None:
        known = ", ".join(f"{k.name} ({t.__name__})" for t, k in _BY_TYPE.items())
        raise UnknownKindError(f"{cls.__name__} is not the observation of any registered landmark kind "
                               f"(registered: {known or 'none'})")
    return kind


def is_observation(obs: Any) -> bool:
    """Whether ``obs`` is an observation of a registered kind."""
    try:
        kind_of(obs)
    except UnknownKindError:
        return False
    return True


def kind_of_symbol(symbol: str) -> LandmarkKind:
    """The kind whose landmarks carry key character ``symbol``."""
    global _BY_SYMBOL
    if _BY_SYMBOL is None:
        _BY_SYMBOL = {k.symbol: k for k in all_kinds()}
    kind = _BY_SYMBOL.get(symbol)
    if kind is not None:
        return kind
    raise UnknownKindError(f"no landmark kind uses key symbol {symbol!r}; registered: "
                           f"{ {k.symbol: k.name for k in _KINDS.values()} }")


def kind_code(name: str) -> int:
    """A small integer naming kind ``name`` in per-landmark arrays (stable within a process)."""
    kind_named(name)
    return _CODES[name]


ROCKS = register_kind(LandmarkKind(
    name="rocks", measurement="reloc.measurements:RockObservations", rank=FIRST_KIND_RANK, symbol="l",
    bag="reloc.rock_bag:ROCK_CODEC", ekf="ekf.rocks:RockUpdate", smoother="fgslam.smoother.rocks:RockLandmarks",
    relocalizer="fgslam.relocalizer:Relocalizer", catalog="fgslam.io.catalog_csv:ROCK_CATALOG_FILE",
    rerun="fgslam.viz.landmarks:PointLandmarkLogger",
))
CRATERS = register_kind(LandmarkKind(
    name="craters", measurement="reloc.craters:CraterObservations", rank=FIRST_KIND_RANK + 1, symbol="r",
    bag="reloc.crater_bag:CRATER_CODEC", ekf="ekf.craters:CraterUpdate", smoother="fgslam.smoother.craters:CraterLandmarks",
    relocalizer="fgslam.crater_relocalizer:CraterRelocalizer", catalog="fgslam.io.crater_csv:CRATER_CATALOG_FILE",
    rerun="fgslam.viz.craters:CraterLogger",
))

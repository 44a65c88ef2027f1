"""The EKF's side of the landmark-kind seam: what a kind's EKF layer provides, and the dispatch.

Landmarks of every kind share the filter state's landmark block (3D points in world, see
:mod:`ekf.state`); the landmark book tags each with its kind's code, so a kind's update only
associates with, and maps, its own landmarks, while hygiene and the bound on the state
(``EkfConfig.max_landmarks``) are the filter's. A kind's EKF layer (``LandmarkKind.ekf``) is a
class built as ``cls(config, kind)`` with:

- ``check(obs)``: validate one observation (raise :class:`ekf.errors.EkfInputError`);
- ``update(state, obs, count)``: the update on the state in place, returning a
  :class:`reloc.backend.LandmarkUpdateReport`; the history replay calls it again with ``count``
  False (counters stay one per input), so it must depend on the state and the observation only;
- ``landmark_map(state)``: the kind's confirmed landmarks as a :class:`reloc.backend.LandmarkMap`;
- ``counts``: a dict of integer counters for ``stats().extra``;
- optionally ``config_class``: a frozen dataclass of its own settings, built from
  ``EkfConfig.kinds[name]`` (:func:`kind_config`).
"""

from __future__ import annotations

from typing import Any, Protocol

from ekf.config import EkfConfig
from ekf.errors import EkfInputError
from ekf.state import FilterState
from reloc.backend import LandmarkMap, LandmarkUpdateReport
from reloc.config import config_from_dict, config_to_dict
from reloc.kinds import (
    KindLayerError,
    LandmarkKind,
    UnknownKindError,
    kind_named,
    kind_of,
    kinds_with,
)


class EkfKindUpdate(Protocol):
    """One landmark kind's update of the filter (see module doc)."""

    counts: dict[str, int]

    def check(self, obs: Any) -> None: ...

    def update(self, s: FilterState, obs: Any, count: bool = True) -> LandmarkUpdateReport: ...

    def landmark_map(self, s: FilterState) -> LandmarkMap: ...


def kind_config(cls: type, kind: LandmarkKind, config: EkfConfig) -> Any:
    """The resolved config of ``kind``'s EKF layer ``cls`` (None when it declares none)."""
    cfg_cls = getattr(cls, "config_class", None)
    if cfg_cls is None:
        return None
    return config_from_dict(cfg_cls, config.kinds.get(kind.name), where=f"ekf.kinds.{kind.name}.")


def resolved_kind_configs(config: EkfConfig) -> dict[str, dict]:
    """Every registered kind's resolved EKF settings, by kind name (for the saved config)."""
    out = {}
    for kind in kinds_with("ekf"):
        cls = kind.layer("ekf")
        cfg = kind_config(cls, kind, config)
        if cfg is not None:
            out[kind.name] = config_to_dict(cfg)
    return out


class KindUpdates:
    """The filter's kind updates, built on first use of each kind."""

    def __init__(self, config: EkfConfig) -> None:
        self.config = config
        self._by_type: dict[type, EkfKindUpdate] = {}
        self._by_name: dict[str, EkfKindUpdate] = {}
        for name in config.kinds:  # overrides of a kind that does not exist: refused up front
            try:
                if not kind_named(name).has("ekf"):
                    raise EkfInputError(f"EkfConfig.kinds[{name!r}]: kind {name!r} has no EKF layer")
            except UnknownKindError as exc:
                raise EkfInputError(f"EkfConfig.kinds: {exc}") from None

    def for_obs(self, obs: Any) -> EkfKindUpdate:
        """The update of ``obs``'s kind; :class:`EkfInputError` for an unregistered type or a kind
        without an EKF layer."""
        upd = self._by_type.get(type(obs))
        if upd is None:
            try:
                kind = kind_of(obs)
            except UnknownKindError as exc:
                raise EkfInputError(f"the EKF cannot observe {type(obs).__name__} at t={getattr(obs, 't', '?')}: "
                                    f"{exc}") from None
            upd = self._build(kind)
            self._by_type[type(obs)] = upd
        return upd

    def named(self, name: str) -> EkfKindUpdate | None:
        """The update of kind ``name`` if it has been used (raises for an unregistered name)."""
        try:
            kind = kind_named(name)
        except UnknownKindError as exc:
            raise EkfInputError(str(exc)) from None
        return self._by_name.get(kind.name)

    def _build(self, kind: LandmarkKind) -> EkfKindUpdate:
        try:
            cls = kind.layer("ekf")
        except KindLayerError as exc:
            raise EkfInputError(f"the EKF cannot observe kind {kind.name!r}: {exc}") from None
        upd = cls(self.config, kind)
        self._by_name[kind.name] = upd
        return upd

    def counts(self) -> dict[str, int]:
        """Every used kind's counters (summed where two kinds share a counter name)."""
        out: dict[str, int] = {}
        for upd in self._by_name.values():
            for k, v in upd.counts.items():
                out[k] = out.get(k, 0) + int(v)
        return out

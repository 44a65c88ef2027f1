"""A back-end's per-kind layers (the EKF's updates, the smoother's layers), and the per-kind
settings they read, on top of the registry of :mod:`reloc.kinds`."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from reloc.kinds import (
    KindLayerError,
    LandmarkKind,
    UnknownKindError,
    kind_named,
    kind_of,
    kinds_with,
)


class KindLayers:
    """A back-end's instances of one layer (``"ekf"``, ``"smoother"``), one per kind, built on first
    use by ``build(kind)`` and kept in creation order; every failure is ``error`` (the back-end's
    own exception) naming the input. ``overrides`` (kind name -> settings) must name registered
    kinds that have the layer."""

    def __init__(self, layer: str, build: Callable[[LandmarkKind], Any], error: type[Exception], owner: str,
                 overrides: Mapping[str, Any] | None = None) -> None:
        self.layer, self._build_fn, self.error, self.owner = layer, build, error, owner
        self._by_type: dict[type, Any] = {}
        self._by_name: dict[str, Any] = {}
        for name in overrides or {}:
            if not self._kind(name, f"{owner}'s kinds setting").has(layer):
                raise error(f"{owner}'s kinds setting names {name!r}, a kind with no {layer} layer")

    def _kind(self, name: str, where: str) -> LandmarkKind:
        try:
            return kind_named(name)
        except UnknownKindError as exc:
            raise self.error(f"{where}: {exc}") from None

    def for_obs(self, obs: Any) -> Any:
        """The instance for ``obs``'s kind (unregistered type, or kind without the layer: ``error``)."""
        inst = self._by_type.get(type(obs))
        if inst is None:
            try:
                kind = kind_of(obs)
            except UnknownKindError as exc:
                raise self.error(f"the {self.owner} cannot observe {type(obs).__name__} at "
                                 f"t={getattr(obs, 't', '?')}: {exc}") from None
            inst = self.get(kind.name)
            self._by_type[type(obs)] = inst
        return inst

    def named(self, name: str) -> Any | None:
        """The instance of kind ``name`` if it has been used (an unregistered name: ``error``)."""
        return self._by_name.get(self._kind(name, f"the {self.owner}").name)

    def get(self, name: str) -> Any:
        """The instance of kind ``name``, built if not used yet."""
        kind = self._kind(name, f"the {self.owner}")
        inst = self._by_name.get(kind.name)
        if inst is None:
            if not kind.has(self.layer):
                raise self.error(f"the {self.owner} cannot observe kind {kind.name!r}: "
                                 f"landmark kind {kind.name!r} has no {self.layer} layer")
            try:
                inst = self._build_fn(kind)
            except KindLayerError as exc:
                raise self.error(f"the {self.owner} cannot observe kind {kind.name!r}: {exc}") from None
            self._by_name[kind.name] = inst
        return inst

    def used(self) -> list:
        return list(self._by_name.values())


def layer_config(cls: type, kind: LandmarkKind, overrides: Mapping[str, Any], where: str) -> Any:
    """The resolved settings of ``kind``'s layer class ``cls``: its ``config_class`` built from
    ``overrides[kind.name]`` (None when the layer declares no config)."""
    from reloc.config import config_from_dict

    cfg_cls = getattr(cls, "config_class", None)
    if cfg_cls is None:
        return None
    return config_from_dict(cfg_cls, overrides.get(kind.name), where=f"{where}.kinds.{kind.name}.")


def config_with_kinds(config: Any, layer: str, where: str) -> dict:
    """A back-end's ``config`` (with a ``kinds`` field of overrides) as a plain dict whose
    ``kinds`` holds every registered kind's resolved settings of ``layer``."""
    from reloc.config import config_to_dict

    out = config_to_dict(config)
    out["kinds"] = {**out["kinds"], **resolved_layer_configs(layer, config.kinds, where)}
    return out


def resolved_layer_configs(layer: str, overrides: Mapping[str, Any], where: str) -> dict[str, dict]:
    """Every registered kind's resolved settings of ``layer``, by kind name (for a saved config)."""
    from reloc.config import config_to_dict

    out = {}
    for kind in kinds_with(layer):
        cfg = layer_config(kind.layer(layer), kind, overrides, where)
        if cfg is not None:
            out[kind.name] = config_to_dict(cfg)
    return out

"""Frozen-dataclass configs: defaults live in code, YAML/dicts only override.

``config_from_dict(Cls, {...})`` builds a (nested) frozen dataclass, rejecting unknown keys with a
:class:`~reloc.errors.ConfigError` that names them; ``config_to_dict`` gives the resolved values back
so that every run can save the config it actually used.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

from reloc.errors import ConfigError

T = TypeVar("T")


def config_to_dict(cfg: Any) -> Any:
    """Plain dict/list/scalar view of a (nested) dataclass config, YAML-serialisable."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: config_to_dict(v) for k, v in cfg.items()}
    if hasattr(cfg, "value") and hasattr(type(cfg), "__members__"):  # Enum
        return cfg.value
    return cfg


def config_from_dict(cls: type[T], data: dict | None, *, base: T | None = None, where: str = "") -> T:
    """Build ``cls`` from ``base`` (or the defaults) overridden by ``data``; nested dataclasses recurse."""
    obj = base if base is not None else cls()
    if not data:
        return obj
    if not isinstance(data, dict):
        raise ConfigError(f"config {where or cls.__name__} must be a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown key(s) {unknown} in config {where or cls.__name__}; known: {sorted(fields)}"
        )
    hints = typing.get_type_hints(cls)
    changes = {}
    for key, value in data.items():
        hint = hints.get(key)
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = config_from_dict(type(current), value, base=current, where=f"{where}{key}.")
        elif isinstance(current, tuple) and isinstance(value, list):
            changes[key] = tuple(value)
        elif isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
            changes[key] = float(value)
        elif hasattr(type(current), "__members__") and isinstance(value, str):  # Enum
            changes[key] = type(current)(value)
        else:
            changes[key] = value
        del hint
    return dataclasses.replace(obj, **changes)

"""Frozen-dataclass configs: defaults live in code, YAML/dicts only override, every value is checked.

Two checks share one declaration, the field's annotation: its type (``float``, ``int``, ``bool``,
``str``, an ``Enum``, a ``Literal`` of choices, a tuple, a nested config) and its range
(``Positive``, ``NonNegative``, ``PositiveInt``, ... or any ``Annotated[float, Gt(..), Le(..)]``):

- at load time, :func:`config_from_dict` validates a YAML/dict override strictly with pydantic
  (JSON rules: ``"2.0"`` is no number, ``2.5`` no integer, ``"no"`` no boolean, NaN and inf are
  rejected, unknown keys too) and names the dotted key of every bad value;
- on construction, :func:`checked` (a class decorator) makes ``__post_init__`` check every
  numeric field's finiteness and range and every ``Literal`` choice, so a config built in code
  (or by ``dataclasses.replace``) cannot hold what a YAML file could not.

``config_to_dict`` gives the resolved values back, so that every run saves the config it used;
``config_from_dict(Cls, config_to_dict(cfg)) == cfg``.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import numbers
import types
import typing
from typing import Annotated, Any, Literal, TypeVar, Union

from annotated_types import Ge, Gt, Interval, Le, Lt

from reloc.errors import ConfigError

T = TypeVar("T")

__all__ = [
    "Ge", "Gt", "Interval", "Le", "Lt", "NonNegative", "NonNegativeInt", "Positive",
    "PositiveInt", "checked", "config_from_dict", "config_to_dict",
]

Positive = Annotated[float, Gt(0)]
NonNegative = Annotated[float, Ge(0)]
PositiveInt = Annotated[int, Ge(1)]
NonNegativeInt = Annotated[int, Ge(0)]

_BOUNDS = (("gt", ">", lambda v, b: v > b), ("ge", ">=", lambda v, b: v >= b),
           ("lt", "<", lambda v, b: v < b), ("le", "<=", lambda v, b: v <= b))


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


# -- field specs (shared by both checks) ---------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _Spec:
    """What a field's annotation asks of its value: ``kind`` "number"/"int"/"choice"/"other"."""

    kind: str
    optional: bool = False
    bounds: tuple[tuple[str, float], ...] = ()
    choices: tuple = ()
    nested: type | None = None


def _spec(hint) -> _Spec:
    optional = False
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        if len(args) != 1:
            return _Spec("other", optional)
        hint, origin = args[0], typing.get_origin(args[0])
    bounds: list[tuple[str, float]] = []
    if origin is Annotated:
        hint, *meta = typing.get_args(hint)
        for m in meta:
            for name, _, _ in _BOUNDS:
                if getattr(m, name, None) is not None:
                    bounds.append((name, getattr(m, name)))
        origin = typing.get_origin(hint)
    if origin is Literal:
        return _Spec("choice", optional, choices=typing.get_args(hint))
    if hint is float:
        return _Spec("number", optional, tuple(bounds))
    if hint is int:
        return _Spec("int", optional, tuple(bounds))
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return _Spec("other", optional, nested=hint)
    return _Spec("other", optional)


@functools.cache
def _specs(cls: type) -> dict[str, _Spec]:
    hints = typing.get_type_hints(cls, include_extras=True)
    return {f.name: _spec(hints[f.name]) for f in dataclasses.fields(cls)}


def _range_text(bounds) -> str:
    sym = {name: s for name, s, _ in _BOUNDS}
    return " and ".join(f"{sym[name]} {b:g}" for name, b in bounds)


def _problem(spec: _Spec, value) -> str | None:
    """Why ``value`` does not fit ``spec`` (None when it does)."""
    if value is None:
        return None if spec.optional or spec.kind == "other" else "must be set (got null)"
    if spec.kind == "choice":
        return None if value in spec.choices else f"must be one of {list(spec.choices)}, got {value!r}"
    if spec.kind not in ("number", "int"):
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return f"must be a number, got {value!r}"
    if spec.kind == "int" and not isinstance(value, numbers.Integral):
        return f"must be an integer, got {value!r}"
    if not math.isfinite(value):
        return f"must be finite, got {value!r}"
    ok = {name: test for name, _, test in _BOUNDS}
    if not all(ok[name](value, b) for name, b in spec.bounds):
        return f"must be {_range_text(spec.bounds)}, got {value!r}"
    return None


def checked(error: type[Exception] = ConfigError):
    """Class decorator (under ``@dataclass``): on construction, every numeric field must be finite
    and inside the range its annotation declares, every ``Literal`` field one of its choices; the
    first violation raises ``error`` naming ``Class.field``. The class's own ``__post_init__``
    (cross-field rules) runs after."""

    def wrap(cls):
        own = cls.__dict__.get("__post_init__")

        def __post_init__(self) -> None:
            for name, spec in _specs(type(self)).items():
                problem = _problem(spec, getattr(self, name))
                if problem:
                    raise error(f"{type(self).__name__}.{name} {problem}")
            if own is not None:
                own(self)

        __post_init__.__doc__ = own.__doc__ if own is not None else None
        cls.__post_init__ = __post_init__
        return cls

    return wrap


# -- load time: strict validation of a YAML/dict override ---------------------------------------

@functools.cache
def _adapter(cls: type):
    from pydantic import ConfigDict, TypeAdapter

    # strict JSON rules (a list is a tuple, a string names an Enum member; nothing else converts),
    # no NaN/inf, no unknown keys; nested configs inherit it
    if "__pydantic_config__" not in cls.__dict__:
        cls.__pydantic_config__ = ConfigDict(strict=True, allow_inf_nan=False, extra="forbid")
    return TypeAdapter(cls)


def merged_overrides(base: dict, over: dict) -> dict:
    """``over`` laid on ``base``, mappings merged key by key at every depth (an override of one
    setting of a section keeps the section's others); neither argument is changed. For override
    mappings before they become a config (:func:`config_from_dict` merges into a config's view)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merged_overrides(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _merge(cls: type, base: dict, data: dict) -> dict:
    """``base`` (a config_to_dict view) overridden by ``data``; nested configs merge key by key,
    so a partial section keeps the other defaults of that field (not of its class)."""
    out = dict(base)
    specs = _specs(cls)
    for key, value in data.items():
        spec = specs.get(key)
        if spec is not None and spec.nested is not None and isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(spec.nested, out[key], value)
        else:
            out[key] = value
    return out


def _owner(cls: type, loc: tuple) -> type | None:
    for part in loc:
        spec = _specs(cls).get(str(part)) if dataclasses.is_dataclass(cls) else None
        if spec is None or spec.nested is None:
            return None
        cls = spec.nested
    return cls


def _leaf_problem(cls: type, loc: tuple, value) -> str | None:
    """The construction-time wording for a bad number or choice (so both checks read alike)."""
    owner = _owner(cls, loc[:-1]) if loc else None
    spec = _specs(owner).get(str(loc[-1])) if owner is not None else None
    return _problem(spec, value) if spec is not None else None


def _describe(cls: type, exc, where: str) -> str:
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        key = (where + ".".join(str(p) for p in loc)).rstrip(".")
        kind, value = err["type"], err.get("input")
        if kind == "unexpected_keyword_argument":
            owner = _owner(cls, loc[:-1])
            known = sorted(f.name for f in dataclasses.fields(owner)) if owner else []
            lines.append(f"unknown key {key!r}" + (f" (known keys here: {', '.join(known)})" if known else ""))
        elif kind in ("dataclass_type", "dataclass_exact_type", "model_type"):
            lines.append(f"{key or 'the config'} must be a mapping of keys to values, got {value!r}")
        elif (problem := _leaf_problem(cls, loc, value)) is not None:
            lines.append(f"{key} {problem}")
        elif kind == "value_error":
            text = str(err.get("ctx", {}).get("error", err["msg"]))
            lines.append(f"{key}: {text}" if key else text)
        else:
            msg = err["msg"][:1].lower() + err["msg"][1:]
            lines.append(f"{key}: {msg}, got {value!r}")
    return "; ".join(dict.fromkeys(lines))


def config_from_dict(cls: type[T], data: dict | None, *, base: T | None = None, where: str = "") -> T:
    """Build ``cls`` from ``base`` (or the defaults) overridden by ``data`` (nested sections merge
    key by key), validated strictly (see module doc); a :class:`ConfigError` names every bad key,
    prefixed by ``where`` (e.g. "relocalizer.")."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config {where.rstrip('.') or cls.__name__} must be a mapping of keys to values, "
                          f"got {type(data).__name__} {data!r}")
    merged = _merge(cls, config_to_dict(base if base is not None else cls()), data)
    try:
        text = json.dumps(merged, default=str)
    except (TypeError, ValueError) as exc:  # e.g. a YAML mapping used as a key
        raise ConfigError(f"config {where.rstrip('.') or cls.__name__}: not a plain mapping of keys to values ({exc})") from None
    from pydantic import ValidationError

    try:
        return _adapter(cls).validate_json(text)
    except ValidationError as exc:
        raise ConfigError(_describe(cls, exc, where)) from None

"""Back-end constructors by name: "ekf" (ekf.EkfSlam), "isam2" (fgslam.smoother.Isam2Smoother), "dr".

Each constructor takes the initial :class:`reloc.backend.PoseEstimate` and an optional config
mapping (overrides of the back-end's frozen config dataclass, see reloc.config).
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from fgslam.errors import FgslamError
from reloc.backend import Backend, PoseEstimate
from reloc.config import config_from_dict

# name -> (module, class); the config class is read from the constructor's annotation
_SPECS: dict[str, tuple[str, str]] = {
    "ekf": ("ekf", "EkfSlam"),
    "isam2": ("fgslam.smoother", "Isam2Smoother"),
    "dr": ("fgslam.backends.dead_reckoning", "DeadReckoning"),
}
BACKEND_NAMES = tuple(_SPECS)


class BackendUnavailableError(FgslamError):
    """The named back-end is unknown or its package is not importable."""


def backend_class(name: str) -> type:
    """The class implementing back-end ``name`` (ImportError becomes BackendUnavailableError)."""
    if name not in _SPECS:
        raise BackendUnavailableError(f"unknown back-end {name!r}; choose from {list(_SPECS)}")
    module, cls = _SPECS[name]
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as exc:
        raise BackendUnavailableError(f"back-end {name!r} ({module}.{cls}) is not available: {exc}") from exc


def available_backends() -> list[str]:
    """Names of the back-ends that import."""
    out = []
    for name in _SPECS:
        try:
            backend_class(name)
            out.append(name)
        except BackendUnavailableError:
            pass
    return out


def _config_class(cls: type) -> type | None:
    import inspect

    try:
        hint = inspect.signature(cls.__init__).parameters.get("config")
    except (TypeError, ValueError):
        return None
    if hint is None:
        return None
    ann = hint.annotation
    if isinstance(ann, str):
        mod = importlib.import_module(cls.__module__)
        name = ann.split("|")[0].strip()
        ann = getattr(mod, name, None)
    return ann if dataclasses.is_dataclass(ann) else None


def backend_config(name: str, overrides: dict | None = None, where: str | None = None) -> Any:
    """The config of back-end ``name``: its defaults with ``overrides`` applied, every key checked
    (:func:`reloc.config.config_from_dict`); None for a back-end without a config class. Errors
    name the keys under ``where`` (default "<name>.")."""
    where = f"{name}." if where is None else where
    if overrides is not None and not isinstance(overrides, dict):
        raise BackendUnavailableError(f"{where.rstrip('.')} must be a mapping of config overrides, got {overrides!r}")
    if name not in _SPECS:
        raise BackendUnavailableError(f"{where.rstrip('.')}: unknown back-end {name!r}; choose from {list(_SPECS)}")
    cfg_cls = _config_class(backend_class(name))
    if cfg_cls is None:
        if overrides:
            raise BackendUnavailableError(f"back-end {name!r} takes no config overrides, got {sorted(overrides)}")
        return None
    return config_from_dict(cfg_cls, overrides, where=where)


def make_backend(name: str, initial: PoseEstimate, overrides: dict | None = None) -> Backend:
    """Construct back-end ``name`` at ``initial`` with config ``overrides`` applied to its defaults;
    from a lost start (position sigma above :data:`fgslam.backends.reanchor.LOST_SIGMA_M`) it
    re-anchors on its first fix (:class:`fgslam.backends.reanchor.Reanchoring`)."""
    from fgslam.backends.reanchor import Reanchoring, is_lost

    cls, cfg = backend_class(name), backend_config(name, overrides)
    if name != "dr" and is_lost(initial):
        return Reanchoring(lambda start: cls(start, cfg), initial)
    return cls(initial, cfg)


def backend_config_dict(backend: Backend) -> dict:
    """The resolved config of a constructed back-end, as a plain dict (every value, defaults
    included; each landmark kind's settings resolved too)."""
    return type(getattr(backend, "inner", backend)).resolved_config(backend.config)


def resolved_config(name: str, overrides: dict | None = None) -> dict:
    """The config back-end ``name`` would run with under ``overrides``, resolved (see
    :func:`backend_config_dict`), without constructing it."""
    cls = backend_class(name)
    cfg_cls = _config_class(cls)
    if cfg_cls is None:
        if overrides:
            raise BackendUnavailableError(f"back-end {name!r} takes no config overrides, got {sorted(overrides)}")
        return {}
    return cls.resolved_config(config_from_dict(cfg_cls, overrides, where=f"{name}."))


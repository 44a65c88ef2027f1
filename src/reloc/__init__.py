"""reloc: the front-end shared by both back-ends.

Typed measurements, the back-end protocol, odometry assembly, stereo measurement model and data
association, triangle descriptors, geometric hashing and the constellation matcher.

The matcher's public names (``Catalog``, ``ConstellationMatcher``, ``MatchResult``,
``MatcherConfig``) are loaded on first use, so ``import reloc`` stays light (no scipy).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from reloc.errors import ConfigError, MeasurementError, RelocError

if TYPE_CHECKING:
    from reloc.catalog import Catalog
    from reloc.matcher import ConstellationMatcher, MatcherConfig, MatchResult

__all__ = [
    "Catalog",
    "ConfigError",
    "ConstellationMatcher",
    "MatchResult",
    "MatcherConfig",
    "MeasurementError",
    "RelocError",
]

_LAZY = {
    "Catalog": "reloc.catalog",
    "ConstellationMatcher": "reloc.matcher",
    "MatcherConfig": "reloc.matcher",
    "MatchResult": "reloc.match_result",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'reloc' has no attribute {name!r}")

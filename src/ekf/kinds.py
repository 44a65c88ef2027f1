"""The EKF's side of the landmark-kind seam: what a kind's EKF layer provides.

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

The filter keeps them in a :class:`reloc.kind_layers.KindLayers` (built on first use, errors as
:class:`ekf.errors.EkfInputError`).
"""

from __future__ import annotations

from typing import Any, Protocol

from ekf.config import EkfConfig
from ekf.errors import EkfInputError
from ekf.state import FilterState
from reloc.backend import LandmarkMap, LandmarkUpdateReport
from reloc.kind_layers import KindLayers, config_with_kinds, layer_config
from reloc.kinds import LandmarkKind


class EkfKindUpdate(Protocol):
    """One landmark kind's update of the filter (see module doc)."""

    counts: dict[str, int]

    def check(self, obs: Any) -> None: ...

    def update(self, s: FilterState, obs: Any, count: bool = True) -> LandmarkUpdateReport: ...

    def landmark_map(self, s: FilterState) -> LandmarkMap: ...


def kind_config(cls: type, kind: LandmarkKind, config: EkfConfig) -> Any:
    """The resolved config of ``kind``'s EKF layer ``cls`` (None when it declares none)."""
    return layer_config(cls, kind, config.kinds, "ekf")


def resolved_ekf_config(config: EkfConfig) -> dict:
    """The resolved config as a plain dict, every registered kind's EKF settings in ``kinds``."""
    return config_with_kinds(config, "ekf", "ekf")


def kind_updates(config: EkfConfig) -> KindLayers:
    """The filter's kind updates, each built as ``cls(config, kind)`` on first use."""
    return KindLayers("ekf", lambda kind: kind.layer("ekf")(config, kind), EkfInputError, "EKF", config.kinds)


def kind_counts(updates: KindLayers) -> dict[str, int]:
    """Every used kind's counters (summed where two kinds share a counter name)."""
    out: dict[str, int] = {}
    for upd in updates.used():
        for k, v in upd.counts.items():
            out[k] = out.get(k, 0) + int(v)
    return out

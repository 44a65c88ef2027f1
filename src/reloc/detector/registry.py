"""Orbital detectors by landmark kind: the one place a new kind registers its detector.

``orbital_detector("crater", model=None, config=None)`` builds the detector of a landmark kind
for nadir (orbital) images; every registered detector has ``detect(image)`` returning detections
with ``centers_px`` (N, 2), ``sizes_px`` ((N,) diameters or (N, 2) box sides) and ``score`` (N,),
which :func:`reloc.detector.catalog.catalog_from_detections` turns into a catalog.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from reloc.detector.errors import DetectorError

OrbitalDetectorFactory = Callable[..., object]
_ORBITAL: dict[str, OrbitalDetectorFactory] = {}


def register_orbital_detector(landmark: str, factory: OrbitalDetectorFactory) -> None:
    """Register ``factory(model_path or None, DetectorConfig or None, **options)`` for ``landmark``."""
    _ORBITAL[landmark] = factory


def orbital_landmarks() -> tuple[str, ...]:
    """The landmark kinds with an orbital detector."""
    return tuple(_ORBITAL)


def orbital_detector(landmark: str, model: str | Path | None = None, config=None, **options):
    """The orbital detector of ``landmark`` (``model``: its ONNX file, default the shipped one;
    ``options``: the kind's own settings, e.g. ``nodata`` for craters)."""
    if landmark not in _ORBITAL:
        raise DetectorError(f"no orbital detector for landmark kind {landmark!r}; known: {', '.join(_ORBITAL)}")
    return _ORBITAL[landmark](None if model is None else Path(model), config, **options)


def _rock(model: Path | None, config) -> object:
    from reloc.detector.runtime import DetectorConfig, RockDetector

    return RockDetector(model, kind="nadir", config=config or DetectorConfig())


def _crater(model: Path | None, config, nodata: float | None = None) -> object:
    from reloc.detector.craters import CraterConfig, CraterDetector
    from reloc.detector.runtime import DetectorConfig

    return CraterDetector(model, config=config or DetectorConfig(), crater=CraterConfig(nodata=nodata))


register_orbital_detector("rock", _rock)
register_orbital_detector("crater", _crater)

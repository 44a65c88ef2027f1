"""Kilometre-scale worlds, generated lazily per tile, and the streaming simulator that drives,
senses and writes the bag as it goes (see docs/sim.md, "Orbital-scale worlds").

Modules: ``config`` (TiledWorldConfig), ``presets`` (plains-2km, rocky-1km, cratered-3km,
sparse-5km; :func:`preset_config`), ``noise`` (seamless fractal terrain), ``world``
(:class:`TiledWorld`: tiles of terrain, rocks, craters, ejecta; bounded cache), ``route``
(strategic waypoints and local avoidance), ``stream`` (:func:`simulate_to_bag`,
:func:`iter_measurements`), ``orbital`` (GeoTIFF image, rock and crater catalogs, crater truth).
This package's ``__init__`` imports nothing eagerly (``sim.config`` uses ``sim.tiled.config``);
the names below load on first use.
"""

_EXPORTS = {
    "TILED_PRESETS": "sim.tiled.presets", "preset_config": "sim.tiled.presets",
    "resolve_tiled_config": "sim.tiled.presets", "backend_calibration": "sim.tiled.presets",
    "TiledWorld": "sim.tiled.world", "TiledSimulation": "sim.tiled.stream", "iter_measurements": "sim.tiled.stream",
    "simulate_to_bag": "sim.tiled.outputs", "TiledRun": "sim.tiled.outputs", "revisits": "sim.tiled.route",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'sim.tiled' has no attribute {name!r}")

"""Kilometre-scale worlds, generated lazily per tile, and the streaming simulator that drives,
senses and writes the bag as it goes (see docs/sim.md, "Orbital-scale worlds").

Modules: ``config`` (TiledWorldConfig), ``presets`` (plains-2km, rocky-1km, cratered-3km,
sparse-5km; :func:`preset_config`), ``noise`` (seamless fractal terrain), ``world``
(:class:`TiledWorld`: tiles of terrain, rocks, craters, ejecta; bounded cache), ``route``
(strategic waypoints and local avoidance), ``stream`` (:func:`simulate_to_bag`,
:func:`iter_measurements`), ``orbital`` (GeoTIFF image, rock and crater catalogs, crater truth).
This package's ``__init__`` imports nothing so that ``sim.config`` can use ``sim.tiled.config``.
"""

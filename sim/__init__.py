"""sim: the Mars-yard simulator (worlds, rover, sensors, orbital catalog, bag writer)."""

from sim.errors import SimError

__all__ = ["SimError"]

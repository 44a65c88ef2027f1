"""sim: the Mars-yard simulator (worlds, rover, sensors, orbital catalog, bag writer).

``simulate(SimConfig(world="my2021", seed=0))`` returns a :class:`SimRun`: time-ordered
measurements, ground truth, the orbital catalog, the true rocks and the world.
"""

from sim.config import (
    CmdConfig,
    ImuConfig,
    OrbitalConfig,
    RoverConfig,
    SensorsConfig,
    SimConfig,
    StereoConfig,
    TraverseConfig,
    WorldGenConfig,
)
from sim.errors import SimError, WorldImportError
from sim.orbital_image import orbital_image
from sim.outputs import write_outputs
from sim.simulate import SimRun, simulate
from sim.world import PRESETS, World, build_world

__all__ = [
    "PRESETS",
    "CmdConfig",
    "ImuConfig",
    "OrbitalConfig",
    "RoverConfig",
    "SensorsConfig",
    "SimConfig",
    "SimError",
    "SimRun",
    "StereoConfig",
    "TraverseConfig",
    "World",
    "WorldGenConfig",
    "WorldImportError",
    "build_world",
    "orbital_image",
    "simulate",
    "write_outputs",
]

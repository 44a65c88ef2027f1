"""Exception base of the ``sim`` package."""

from __future__ import annotations


class SimError(Exception):
    """Base class for every error raised by ``sim``."""


class WorldImportError(SimError, ValueError):
    """A Gazebo world, heightmap or mesh could not be imported."""

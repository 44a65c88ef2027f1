"""Exception base of the ``reloc`` package; every module raises a subclass of :class:`RelocError`."""

from __future__ import annotations


class RelocError(Exception):
    """Base class for every error raised by ``reloc``."""


class MeasurementError(RelocError, ValueError):
    """A measurement is malformed: NaN, wrong shape, non-monotonic time, ..."""


class ConfigError(RelocError, ValueError):
    """A configuration value or file is invalid."""

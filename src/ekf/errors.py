"""Exception base of the ``ekf`` package."""

from __future__ import annotations

from reloc.errors import MeasurementError


class EkfError(Exception):
    """Base class for every error raised by ``ekf``."""


class EkfInputError(EkfError, MeasurementError):
    """An input the filter cannot take: out of order, NaN, wrong shape. The state is left untouched."""

"""Errors of the detectors."""

from reloc.errors import RelocError


class DetectorError(RelocError):
    """A detector model file is missing, corrupt or of an unsupported layout, or an image is bad."""


class ImageError(DetectorError, ValueError):
    """An image a detector cannot use (shape, dtype, no valid pixel)."""

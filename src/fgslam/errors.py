"""Exception base of the ``fgslam`` package; the CLI maps these to exit codes."""

from __future__ import annotations


class FgslamError(Exception):
    """Base class for every error raised by ``fgslam``."""


class InputFileError(FgslamError, ValueError):
    """A user-supplied file (bag, catalog, CSV, config) is missing or malformed."""


class BagError(InputFileError):
    """A ROS 2 bag is malformed, lacks a required topic, or has unrepairable stamps."""


class SmootherError(FgslamError):
    """The iSAM2 smoother rejected an input or failed to update."""

"""reloc: the front-end shared by both back-ends.

Typed measurements, the back-end protocol, odometry assembly, stereo measurement model and data
association, triangle descriptors, geometric hashing and the constellation matcher.
"""

from reloc.errors import ConfigError, MeasurementError, RelocError

__all__ = ["RelocError", "MeasurementError", "ConfigError"]

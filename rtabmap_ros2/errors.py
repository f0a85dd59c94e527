"""The package's exceptions: one base class, one subclass per area.

Messages say what was wrong, with the offending value, and what to do. Only entry points (the
node's ``main``, the command line) turn them into log lines and exit codes.
"""


class RtabmapError(Exception):
    """Base class of every error raised on purpose by rtabmap_ros2."""


class ParameterError(RtabmapError, ValueError):
    """A parameter has an unknown name or a value out of its range."""


class SensorDataError(RtabmapError, ValueError):
    """A sensor frame or message is unusable (wrong encoding, NaN pose, sizes that disagree...)."""


class DatabaseError(RtabmapError):
    """The SQLite long-term memory cannot be opened, read or written."""


class RegistrationError(RtabmapError):
    """A rigid transform between two nodes could not be estimated (too few inliers, no scans...)."""


class OptimizationError(RtabmapError):
    """A pose graph could not be optimised (empty graph, unknown root, solver failure)."""


class BagError(RtabmapError):
    """A bag file is missing, truncated, lacks a topic or holds a message that cannot be read."""


class DatasetError(RtabmapError):
    """A dataset folder (images, TUM RGB-D, CARMEN log) is missing or malformed."""

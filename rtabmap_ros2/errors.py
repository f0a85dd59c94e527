"""The package's exceptions: one base class, one subclass per area.

Messages say what was wrong, with the offending value, and what to do. Only entry points (the
node's ``main``, the command line) turn them into log lines and exit codes.
"""

from __future__ import annotations


class RtabmapError(Exception):
    """Base class of every error raised on purpose by rtabmap_ros2."""


class ParameterError(RtabmapError, ValueError):
    """A parameter has an unknown name or a value out of its range."""


class SensorDataError(RtabmapError, ValueError):
    """A sensor frame or message is unusable (wrong encoding, NaN pose, sizes that disagree...).

    Attributes:
        reason: short, stable name of the fault (``encoding``, ``short_data``, ``no_valid_depth``...):
            the node logs once and counts per (topic, reason).
        source: the part of a frame at fault (``rgb``, ``depth``, ``scan``, ``odom``,
            ``camera_info``), or None when the message itself is named by the caller.
    """

    def __init__(self, message: str, reason: str = "invalid", source: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.source = source


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

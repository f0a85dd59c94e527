"""Bad input dropped by the node: one log line per (topic, reason), a counter per (topic, reason).

The node drops a message (or a synchronised frame) it cannot use and keeps running (CONVENTIONS,
"Errors and logs"). Each fault is named by a short ``reason`` (``SensorDataError.reason``:
``encoding``, ``short_data``, ``no_valid_depth``, ``stamp_not_increasing``...): the first drop of
each (topic, reason) is logged, so a second, different fault on the same topic is seen too, and
every drop is counted. The counters are published on ``info`` as ``node_dropped:<topic>:<reason>``
(and their sum as ``node_dropped_messages``).
"""

from __future__ import annotations

import threading

# Key prefix of the per-(topic, reason) counters in the info DiagnosticArray.
INFO_KEY_PREFIX = "node_dropped"


class DroppedInputs:
    """Counts of dropped inputs per (topic, reason); logs the first of each pair.

    Args:
        logger: an rclpy logger (``warning`` method).
    """

    def __init__(self, logger) -> None:
        self.counts: dict[tuple[str, str], int] = {}
        self._logger = logger
        self._lock = threading.Lock()   # sensor callbacks and the worker both drop inputs

    def drop(self, topic: str, reason: str, message: str) -> None:
        """Count one dropped input; log it when it is the first of its (topic, reason)."""
        with self._lock:
            count = self.counts.get((topic, reason), 0) + 1
            self.counts[(topic, reason)] = count
        if count == 1:
            self._logger.warning(f"dropped bad input on {topic} [{reason}]: {message} "
                                 "(further ones with this reason are counted on info, not logged)")

    def total(self) -> int:
        """Inputs dropped so far, all topics and reasons."""
        with self._lock:
            return sum(self.counts.values())

    def info(self) -> dict[str, int]:
        """``{"node_dropped:<topic>:<reason>": count, ..., "node_dropped_messages": total}`` for ``info``."""
        with self._lock:
            items = sorted(self.counts.items())
        out = {f"{INFO_KEY_PREFIX}:{topic}:{reason}": count for (topic, reason), count in items}
        out[f"{INFO_KEY_PREFIX}_messages"] = sum(count for _, count in items)
        return out


__all__ = ["DroppedInputs", "INFO_KEY_PREFIX"]

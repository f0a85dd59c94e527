"""Polling for a condition another thread makes true (the tests of threaded parts share it)."""

from __future__ import annotations

import time

# How long a test waits for another thread by default: generous, for a loaded 2-core machine.
TIMEOUT_S = 30.0


def wait_for(condition, timeout: float = TIMEOUT_S, poll_s: float = 0.01) -> bool:
    """Whether ``condition()`` became true within ``timeout`` seconds (checked every ``poll_s``)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll_s)
    return bool(condition())

"""One way for the integration tests to spin an rclpy executor in a background thread.

``executor.shutdown()`` while another thread is inside ``executor.spin()`` races with it: shutdown
clears the executor's guard condition under the waiting thread, which then dies with
``AttributeError: 'NoneType' object has no attribute 'handle'`` (pytest's "unhandled thread
exception" warning at the end of a run). Here the thread spins one wait at a time and checks a stop
flag, so it has left the executor before the executor is shut down.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Iterator

# How long one wait of the spin loop may last (s): the longest the stop waits for the thread.
SPIN_WAIT_S = 0.05
JOIN_TIMEOUT_S = 10.0


@contextlib.contextmanager
def spinning(executor) -> Iterator[None]:
    """Spin ``executor`` in a daemon thread for the ``with`` block; then stop the thread, join it
    and shut the executor down (in that order)."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set() and executor.context.ok():
            executor.spin_once(timeout_sec=SPIN_WAIT_S)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=JOIN_TIMEOUT_S)
        executor.shutdown()

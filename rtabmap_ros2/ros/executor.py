"""The executor the node spins in: rclpy's MultiThreadedExecutor, each task handed to its pool once.

rclpy's executor hands out the tasks it made and that have not started yet again before it waits for
new work (``Executor._wait_for_ready_callbacks``: "yield tasks in-progress"), and the
MultiThreadedExecutor submits each of them to its thread pool again. A submitted task starts when a
pool thread gets the interpreter lock, up to the 5 ms switch interval later; until then the spin
thread goes round without ever waiting, holding the lock the pool thread and the core's worker need.
Replaying issue 50's recording at 4x, 97.8 % of the executor's 2,000-2,600 rounds a second were such
repeats, and its thread used 81-182 s of CPU in a replay where the worker used 27-45 s
(docs/benchmarks.md, "Issue 50's recording into the node again").
"""

from __future__ import annotations

import threading
import weakref

from rclpy.executors import (ConditionReachedException, ExternalShutdownException, MultiThreadedExecutor,
                             ShutdownException, TimeoutException)

# How long the spin thread waits for a pool thread to start a task it handed out already (s).
PENDING_WAIT_S = 0.01


class NodeExecutor(MultiThreadedExecutor):
    """A MultiThreadedExecutor that submits a task to its pool once until a pool thread started it:
    handed out again before that, the spin thread waits (up to :data:`PENDING_WAIT_S`) for it to
    start instead of submitting it again. A task that ran and is pending again (a coroutine waiting
    for a future) is submitted again, as rclpy does."""

    def __init__(self, num_threads: int, *, context=None) -> None:
        super().__init__(num_threads, context=context)
        self._started: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
            return
        started = self._started.get(handler)
        if started is not None and not started.is_set():
            started.wait(PENDING_WAIT_S)
            return
        started = threading.Event()
        self._started[handler] = started

        def run() -> None:
            started.set()
            handler()

        self._executor.submit(run)
        self._futures.append(handler)
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()  # raise any exceptions

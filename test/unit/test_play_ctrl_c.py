"""``play``'s Ctrl-C: the handler sets the playback's Event, and must never wait for ever on its lock."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# Ctrl-C arrives while the playback holds the lock that threading.Event.wait holds around its wait
# (the window the CLI hung in, once in CI). The playback runs on a worker thread, so the handler,
# run on the main thread, waits only until the worker lets go of the lock.
SCENARIO = textwrap.dedent("""
    import os, signal, threading, time
    from rtabmap_ros2.cli.cmd_play import _in_worker_thread

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    def play():
        with stop._cond:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.3)
        return stop.wait(5.0)

    print("stopped" if {call} else "not stopped", flush=True)
""")


def _run(call: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCENARIO.format(call=call)], capture_output=True, text=True,
                          timeout=30)


def test_ctrl_c_while_the_playback_holds_its_events_lock_stops_it():
    done = _run("_in_worker_thread(play)")
    assert done.returncode == 0 and done.stdout.strip() == "stopped", done.stderr


def test_the_same_ctrl_c_on_the_playing_thread_would_hang():
    """The failure the worker thread prevents, shown: playback on the main thread never returns."""
    with pytest.raises(subprocess.TimeoutExpired):
        subprocess.run([sys.executable, "-c", SCENARIO.format(call="play()")], capture_output=True, timeout=3)


def test_an_error_in_the_playback_reaches_the_caller():
    done = _run("_in_worker_thread(lambda: 1 / 0)")
    assert done.returncode == 1 and "ZeroDivisionError" in done.stderr

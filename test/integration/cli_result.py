"""One way for the CLI tests to check a refused command: exit 2, one ``error:`` line, no traceback."""

from __future__ import annotations

import subprocess


def error_line(result: subprocess.CompletedProcess) -> str:
    """The one ``error: ...`` line of a command that exited with status 2."""
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, result.stderr
    return lines[0]

"""Output files written safely: a temporary name in the target folder, then a rename.

Exports and backups go to folders other users or programs may write to. Every file is first
created under a fresh random name in the target folder with ``O_CREAT | O_EXCL | O_NOFOLLOW``
(never an existing file, never through a symlink), written, closed, and only then given its name:

* ``exclusive=False`` (exports): ``rename`` over the name. A symlink planted at the name is
  replaced, never followed (rename acts on the directory entry), and readers never see a partly
  written file.
* ``exclusive=True`` (backups): ``link`` to the name, which fails when anything (a file, a
  dangling symlink) already has it, so the name is never followed and nothing is overwritten.

A failed write leaves no temporary file behind. Errors are ``OSError`` (``FileExistsError`` for an
exclusive name in use): callers turn them into their area's exception.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator

# Flags of the temporary file: new (never an existing file), never through a symlink.
_CREATE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
# Permissions before the umask, as open() gives.
_FILE_MODE = 0o666
# Attempts at a free random temporary name (a collision needs 2^64 bad luck or a hostile folder).
_TEMPORARY_ATTEMPTS = 16


def _create_temporary(path: Path) -> tuple[int, Path]:
    """A new file ``.<name>.<random>.tmp`` next to ``path``: (open write descriptor, its path)."""
    for _ in range(_TEMPORARY_ATTEMPTS):
        # os.urandom: what secrets.token_hex reads, without importing secrets (hmac, hashlib: 4 ms).
        tmp = path.with_name(f".{path.name}.{os.urandom(8).hex()}.tmp")
        try:
            return os.open(tmp, _CREATE_FLAGS, _FILE_MODE), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name next to {path}")


def _publish(tmp: Path, path: Path, exclusive: bool) -> None:
    if exclusive:
        os.link(tmp, path, follow_symlinks=False)   # EEXIST if the name is taken, even by a dangling link
        os.unlink(tmp)
    else:
        os.replace(tmp, path)


@contextmanager
def new_path(path: str | os.PathLike, exclusive: bool = False) -> Iterator[Path]:
    """Yield a new, empty temporary file next to ``path`` for a writer that needs a path (SQLite);
    give it ``path``'s name when the block ends without an error, else delete it."""
    path = Path(path)
    fd, tmp = _create_temporary(path)
    os.close(fd)
    try:
        yield tmp
        _publish(tmp, path, exclusive)
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def new_file(path: str | os.PathLike, mode: str = "w", exclusive: bool = False,
             newline: str | None = None) -> Iterator[IO]:
    """Yield a file object (``mode`` "w" or "wb") that becomes ``path`` when the block ends
    without an error (see the module doc); on an error nothing is left at ``path`` or beside it."""
    if mode not in ("w", "wb"):
        raise ValueError(f"new_file: mode {mode!r} is not 'w' or 'wb'")
    path = Path(path)
    fd, tmp = _create_temporary(path)
    try:
        with os.fdopen(fd, mode, newline=newline) if mode == "w" else os.fdopen(fd, mode) as f:
            yield f
        _publish(tmp, path, exclusive)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | os.PathLike, data: bytes, exclusive: bool = False) -> None:
    """``Path.write_bytes`` through :func:`new_file`."""
    with new_file(path, "wb", exclusive) as f:
        f.write(data)


def write_text(path: str | os.PathLike, text: str, exclusive: bool = False) -> None:
    """``Path.write_text`` through :func:`new_file`."""
    with new_file(path, "w", exclusive) as f:
        f.write(text)


__all__ = ["new_file", "new_path", "write_bytes", "write_text"]

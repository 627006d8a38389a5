"""Reading a file the operator names (the config, a prescription map) without trusting it.

A FIFO given as the config made ``check-config`` and ``run`` wait for a writer for ever, and
``/dev/zero`` read until a MemoryError. These files are small documents: only a regular file
is read, opened without blocking (a FIFO's ``open`` itself blocks), and no more than a cap.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


class UnreadableFile(Exception):
    """Why the file cannot be used, in words for the operator (without the path)."""


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def regular_file_problem(path: str | os.PathLike[str],
                         max_bytes: int | None = None) -> str | None:
    """Why ``path`` is not a readable regular file of at most ``max_bytes``, or None.

    Opened for real (as root ``os.access`` says yes to anything), but without blocking."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return "file not found"
    except IsADirectoryError:
        return "a directory, not a file"
    except OSError as exc:
        return f"cannot read the file: {exc.strerror or exc}"
    try:
        info = os.fstat(fd)
    finally:
        os.close(fd)
    if not stat.S_ISREG(info.st_mode):
        kind = _kind(info.st_mode)
        return f"{kind}, not a file" if kind.startswith("a ") else kind
    if max_bytes is not None and info.st_size > max_bytes:
        return f"{info.st_size} bytes, more than the {max_bytes} a file here may have"
    return None


def read_regular_file(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``; ``UnreadableFile`` otherwise."""
    problem = regular_file_problem(path, max_bytes)
    if problem is not None:
        raise UnreadableFile(problem)
    try:
        with Path(path).open("rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise UnreadableFile(f"cannot read the file: {exc.strerror or exc}") from None
    if len(data) > max_bytes:  # it grew since the check
        raise UnreadableFile(f"more than the {max_bytes} bytes a file here may have")
    return data

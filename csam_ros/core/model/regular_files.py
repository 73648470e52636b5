"""Files read and written only when they are regular files: a FIFO, a device or a socket where
a bag, a state file or a summary is expected would hang a reader (a FIFO without writer) or,
replaced by a written file, lose the device. Each refusal is a :class:`NotRegularFileError`,
an OSError naming the file and what it is, which every reader already reports in one line.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path
from typing import BinaryIO

_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a directory"),
)


class NotRegularFileError(OSError):
    """A path that is not a regular file where one is read or replaced."""


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def _refusal(path: os.PathLike[str] | str, mode: int, what: str) -> NotRegularFileError:
    return NotRegularFileError(
        errno.EINVAL, f"{_kind(mode)}, not a regular file; not {what} it", str(path)
    )


def open_regular(path: os.PathLike[str] | str) -> BinaryIO:
    """``path`` opened for binary reading; NotRegularFileError (before any blocking open)
    unless it is a regular file, symbolic links followed."""
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise _refusal(path, mode, "reading")
    # opened without blocking (a FIFO put in its place since would block here), then checked
    # again on the descriptor itself
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise _refusal(path, mode, "reading")
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: os.PathLike[str] | str, limit: int) -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`); OSError (EFBIG) naming
    the file when it holds more than ``limit`` bytes, found before they are read."""
    with open_regular(path) as stream:
        size = os.fstat(stream.fileno()).st_size
        data = stream.read(limit + 1) if size <= limit else b""
    if size > limit or len(data) > limit:  # a file grown since: read no more than the bound
        raise OSError(
            errno.EFBIG, f"{max(size, len(data))} bytes, more than the {limit} read", str(path)
        )
    return data


def check_replaceable(path: os.PathLike[str] | str) -> None:
    """NotRegularFileError unless ``path`` is absent, a regular file or a symbolic link (what
    a rename may replace: the link itself, never what it names)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise _refusal(Path(path), mode, "replacing")

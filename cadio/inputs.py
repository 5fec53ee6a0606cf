"""Reading the files a user names: regular files only, and no more bytes than a limit.

A library folder, a settings file or a recordings folder may hold anything with the right
name: a named pipe blocks the first read until a writer comes (forever, at night), a link to
``/dev/zero`` never ends, a 50 GB file takes the disk's time. ``open_regular`` refuses what is
not a regular file without blocking (it opens non-blocking and checks the open file, so a file
swapped after a check is caught too), and ``read_limited`` stops at a size limit.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from cadio.errors import InputFileError

_KINDS = {stat.S_IFDIR: "a folder", stat.S_IFIFO: "a named pipe",
          stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device",
          stat.S_IFSOCK: "a socket"}


def kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words ("a named pipe", ...)."""
    return _KINDS.get(stat.S_IFMT(mode), "not a regular file")


def open_regular(path: Path | str) -> BinaryIO:
    """Open a regular file for binary reading (links followed).

    Raises:
        InputFileError: the path is a folder, a pipe, a device or a socket (never read).
        OSError: it does not exist or cannot be opened.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise InputFileError(path, f"is {kind(mode)}, not a regular file: not read")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_limited(path: Path | str, max_bytes: int) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``.

    Raises:
        InputFileError: not a regular file, or larger than the limit.
        OSError: it does not exist or cannot be read.
    """
    with open_regular(path) as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise InputFileError(path, f"is larger than {max_bytes / 1e6:g} MB: not read")
    return data


def read_text(path: Path | str, what: str, max_bytes: int = 16 << 20) -> str:
    """A settings file as UTF-8 text (a byte-order mark, as spreadsheets save, is dropped).

    Raises:
        InputFileError: missing, unreadable, not a regular file, too large or not UTF-8;
            the message names the file, ``what`` it is and the reason.
    """
    try:
        return read_limited(path, max_bytes).decode("utf-8-sig")
    except InputFileError as exc:
        raise InputFileError(path, f"{what} {exc.reason}") from None
    except OSError as exc:
        raise InputFileError(path, f"{what} cannot be read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"{what} is not UTF-8 text (byte {exc.start})") from None

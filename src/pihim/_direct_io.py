"""Output files written in one system call, past the page cache where the file system allows.

``pihim polar`` writes 15 to 60 MB of images per frame. Written through the
page cache, the kernel's copy of each byte costs more CPU than computing
it: 20-55 ms of CPU per 20 MB file on the 2-core benchmark machine while a
batch runs, against about 1 ms with direct I/O (``O_DIRECT``: the disk reads
the bytes from this process's page-aligned buffer). Where ``O_DIRECT`` is
refused (tmpfs, systems without it, unaligned block sizes) the same bytes
are written through the page cache. The file's bytes are written as they
are: the caller writes under a temporary name for atomicity. Each thread
keeps one staging buffer, the size of the largest file it wrote (20 MB for
a full-resolution float32 TIFF), freed with the thread.

Direct I/O also bypasses the cache for what it would have absorbed: on a
disk slower than the outputs come, a writer waits for the disk at once
instead of after the kernel's dirty-page limit.
"""

from __future__ import annotations

import errno
import mmap
import os
import threading
from collections.abc import Callable
from pathlib import Path

#: Direct I/O unit: writes are whole blocks of this size from a buffer aligned to it (a multiple of any disk's
#: logical block).
BLOCK = 4096
_BUFFER = threading.local()  # each thread's page-aligned staging buffer


def _staging(n_bytes: int) -> mmap.mmap:
    """This thread's page-aligned buffer of at least ``n_bytes`` (kept for the next file of the same size)."""
    buf = getattr(_BUFFER, "buf", None)
    if buf is None or len(buf) < n_bytes:
        buf = _BUFFER.buf = mmap.mmap(-1, n_bytes)
    return buf


def _write_all(fd: int, data: memoryview) -> None:
    """``os.write`` until every byte of ``data`` is written."""
    done = 0
    while done < len(data):
        done += os.write(fd, data[done:])


def write_file(path: str | Path, length: int, fill: Callable[[mmap.mmap], None]) -> Path:
    """Write a file of ``length`` bytes that ``fill`` puts into a page-aligned buffer, with ``O_DIRECT`` if allowed.

    ``fill(buf)`` writes the file's bytes to ``buf[:length]`` (``buf`` may be
    longer). Direct I/O writes whole 4096-byte blocks, so the file is cut
    back to ``length`` after; where the file system refuses it (EINVAL) the
    same bytes are written through the page cache. Other errors (no space,
    I/O) propagate; ``path`` is written as given (use a temporary name for
    atomicity).
    """
    blocks = max(1, -(-length // BLOCK)) * BLOCK
    buf = _staging(blocks)
    fill(buf)
    view = memoryview(buf)
    direct = getattr(os, "O_DIRECT", 0)
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0)
    if direct:
        try:
            fd = os.open(path, flags | direct, 0o666)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
        else:
            try:
                _write_all(fd, view[:blocks])
                os.ftruncate(fd, length)
                return Path(path)
            except OSError as exc:
                if exc.errno != errno.EINVAL:  # a real failure (no space, I/O error): the caller's to report
                    raise
            finally:
                os.close(fd)
    fd = os.open(path, flags, 0o666)  # through the page cache
    try:
        _write_all(fd, view[:length])
    finally:
        os.close(fd)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """:func:`write_file` of ``data`` (e.g. an encoded PNG)."""
    n = len(data)

    def fill(buf: mmap.mmap) -> None:
        buf[:n] = data

    return write_file(path, n, fill)

"""A small PNG encoder for 8-bit grey and RGB(A) images, tuned for speed.

Rows are stored unfiltered (PNG filter type 0) and the whole image is one
deflate stream at a fast level: with the ``isal`` package (Intel ISA-L,
a dependency of pihim on x86-64 and ARM64) about 4x faster than zlib at a
similar size, else with the standard library's zlib. Both release the GIL, so
several images can be encoded at once on several threads. Level 0 stores
the rows in deflate's uncompressed blocks: a valid PNG the size of its
pixels for the least CPU (``pihim polar --png``'s previews by default).

References
----------
.. [1] W3C, "Portable Network Graphics (PNG) Specification (Third Edition)",
   2025: signature, IHDR / IDAT / IEND chunks, CRC-32, colour types 0, 2, 6.
"""

from __future__ import annotations

import struct
import threading
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

try:  # optional: ISA-L's deflate, zlib-compatible streams, much faster at low levels
    from isal import isal_zlib as _deflate

    #: ISA-L level 1: 3-4x faster than zlib level 1 here, files a few per cent larger at most.
    DEFAULT_LEVEL = 1
except ImportError:  # pragma: no cover - depends on the environment
    _deflate = zlib
    DEFAULT_LEVEL = 1

#: Name of the deflate implementation in use ("isal" or "zlib").
DEFLATE = "isal" if _deflate is not zlib else "zlib"

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPE = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type (grey, RGB, RGBA)


def _chunk(kind: bytes, data: bytes) -> list[bytes]:
    """The parts of one chunk: length, type, data, CRC-32 of type and data (joined once by the caller)."""
    return [struct.pack(">I", len(data)), kind, data, struct.pack(">I", _deflate.crc32(data, zlib.crc32(kind)))]


_ROWS = threading.local()  # each thread's row buffer of the last size it encoded


def _row_buffer(height: int, row_bytes: int) -> NDArray[np.uint8]:
    """A ``(height, row_bytes)`` uint8 buffer, reused by the calling thread while the size stays the same.

    Previews of one camera have one size: reusing the buffer saves faulting
    in megabytes of fresh pages for every image.
    """
    rows = getattr(_ROWS, "buffer", None)
    if rows is None or rows.shape != (height, row_bytes):
        rows = _ROWS.buffer = np.empty((height, row_bytes), dtype=np.uint8)
    return rows


def _checked(image: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], int, int, int]:
    """The image as a C-contiguous ``(H, W * channels)`` array, and H, W, channels (a one-line ValueError else)."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise ValueError("encode_png needs a uint8 (H, W), (H, W, 3) or (H, W, 4) image")
    height, width = img.shape[:2]
    channels = 1 if img.ndim == 2 else img.shape[2]
    if height < 1 or width < 1:
        raise ValueError("encode_png needs a non-empty image")
    return np.ascontiguousarray(img).reshape(height, width * channels), height, width, channels


#: Bytes of one stored deflate block's payload at most (its length field is 16 bits).
_STORED_MAX = 65535


def stored_png(image: NDArray[np.uint8]) -> tuple[int, Callable[[Any], None]] | None:
    """A level-0 PNG of ``image`` laid out straight into a caller's buffer: ``(length, fill)``.

    ``fill(buf)`` writes the file's ``length`` bytes into ``buf`` (a
    writable buffer of at least ``length`` bytes, e.g. the page-aligned one
    of :func:`pihim._direct_io.write_file`), copying the pixels once: each
    stored deflate block holds whole rows, so the rows land in place with
    their filter bytes, and the checksums (Adler-32 of the stream, CRC-32 of
    the chunk) are taken where they lie. ``None`` when a row is longer than
    a stored block (65,535 bytes); :func:`encode_png` then does it.
    """
    pix, height, width, channels = _checked(image)
    row = 1 + width * channels
    if row > _STORED_MAX:
        return None
    per_block = _STORED_MAX // row  # rows in each stored block
    n_full, last = divmod(height, per_block)
    blocks = [(per_block, n_full)] + ([(last, 1)] if last else [])  # (rows per block, blocks)
    zlib_len = 2 + sum(n * (5 + r * row) for r, n in blocks) + 4
    ihdr = struct.pack(">IIBBBBB", width, height, 8, _COLOUR_TYPE[channels], 0, 0, 0)
    head = _SIGNATURE + b"".join(_chunk(b"IHDR", ihdr)) + struct.pack(">I", zlib_len) + b"IDAT"
    length = len(head) + zlib_len + 4 + 12

    def fill(buf: Any) -> None:
        out = np.frombuffer(buf, dtype=np.uint8, count=length)
        out[:len(head)] = np.frombuffer(head, np.uint8)
        pos = len(head)
        out[pos:pos + 2] = (0x78, 0x01)  # zlib header: deflate, 32 KiB window, no dictionary, "fastest"
        pos += 2
        adler, done = 1, 0
        for k, (rows, n) in enumerate(blocks):
            size = rows * row
            view = out[pos:pos + n * (5 + size)].reshape(n, 5 + size)
            view[:, 0] = 0
            view[:, 1:5] = np.frombuffer(struct.pack("<HH", size, size ^ 0xFFFF), np.uint8)
            payload = view[:, 5:].reshape(n, rows, row)
            payload[:, :, 0] = 0  # filter type 0 (none) on every row
            payload[:, :, 1:] = pix[done:done + n * rows].reshape(n, rows, row - 1)
            for b in range(n):
                adler = _deflate.adler32(view[b, 5:], adler)
            if k == len(blocks) - 1:
                view[-1, 0] = 1  # BFINAL on the last block
            pos += n * (5 + size)
            done += n * rows
        out[pos:pos + 4] = np.frombuffer(struct.pack(">I", adler), np.uint8)
        pos += 4
        crc = _deflate.crc32(out[len(head) - 4:pos])  # chunk type and data
        out[pos:pos + 4] = np.frombuffer(struct.pack(">I", crc), np.uint8)
        out[pos + 4:pos + 16] = np.frombuffer(b"".join(_chunk(b"IEND", b"")), np.uint8)

    return length, fill


def encode_png(image: NDArray[np.uint8], *, level: int | None = None) -> bytes:
    """PNG file bytes of a uint8 image.

    Parameters
    ----------
    image : numpy.ndarray, uint8, shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4)
        Grey, RGB or RGBA, rows top to bottom.
    level : int, optional
        Deflate level, 0-9 (default :data:`DEFAULT_LEVEL`: fast). 0 stores
        the rows uncompressed (deflate's stored blocks: the least CPU, a
        file the size of the pixels); 1-3 use ISA-L when installed, higher
        levels zlib.

    Returns
    -------
    bytes
    """
    pix, height, width, channels = _checked(image)
    level = DEFAULT_LEVEL if level is None else int(level)
    if not 0 <= level <= 9:
        raise ValueError(f"a PNG deflate level is 0-9, got {level}")
    if level == 0 and (stored := stored_png(pix.reshape(height, width, channels))) is not None:
        length, fill = stored
        buf = bytearray(length)
        fill(buf)
        return bytes(buf)
    rows = _row_buffer(height, 1 + width * channels)
    rows[:, 0] = 0  # filter type 0 (none) on every row
    rows[:, 1:] = pix  # one copy, no temporary
    ihdr = struct.pack(">IIBBBBB", width, height, 8, _COLOUR_TYPE[channels], 0, 0, 0)
    deflate = _deflate if 1 <= level <= 3 else zlib  # ISA-L has levels 0-3, and no stored blocks at 0
    idat = deflate.compress(rows.data, level)
    return b"".join([_SIGNATURE, *_chunk(b"IHDR", ihdr), *_chunk(b"IDAT", idat), *_chunk(b"IEND", b"")])

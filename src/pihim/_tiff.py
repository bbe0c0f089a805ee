"""Single-page float32 TIFF files, laid out to be written past the page cache.

``pihim polar`` writes 15 to 60 MB of float32 images per frame, with
:func:`pihim._direct_io.write_file` (one system call from a page-aligned
buffer, ``O_DIRECT`` where allowed). The file is baseline TIFF 6.0: the
8-byte header and one image file directory (IFD) in the first 4096 bytes,
then the image, uncompressed, as one strip at offset 4096, so that the
whole file leaves from one buffer with the image block-aligned in it.

References
----------
.. [1] Adobe Developers Association, "TIFF Revision 6.0" (1992): section 2
   (header, IFD, the 12-byte entry), sections 3 and 8 (baseline fields),
   section 19 (SampleFormat 3, IEEE floating point).
"""

from __future__ import annotations

import mmap
import struct
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pihim._direct_io import BLOCK, write_file

#: Offset of the image data: the header and IFD fill the first block.
DATA_OFFSET = BLOCK
_SHORT, _LONG = 3, 4


def tiff_header(height: int, width: int) -> bytes:
    """The first :data:`DATA_OFFSET` bytes of a float32 ``height`` x ``width`` single-strip TIFF."""
    n_bytes = height * width * 4
    entries = [  # (tag, type, value), ascending tags as TIFF requires
        (256, _LONG, width),  # ImageWidth
        (257, _LONG, height),  # ImageLength
        (258, _SHORT, 32),  # BitsPerSample
        (259, _SHORT, 1),  # Compression: none
        (262, _SHORT, 1),  # PhotometricInterpretation: BlackIsZero
        (273, _LONG, DATA_OFFSET),  # StripOffsets (one strip)
        (277, _SHORT, 1),  # SamplesPerPixel
        (278, _LONG, height),  # RowsPerStrip: all
        (279, _LONG, n_bytes),  # StripByteCounts
        (284, _SHORT, 1),  # PlanarConfiguration: chunky
        (339, _SHORT, 3),  # SampleFormat: IEEE float
    ]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHI", tag, kind, 1) + (struct.pack("<HH", value, 0) if kind == _SHORT else struct.pack("<I", value))
        for tag, kind, value in entries) + struct.pack("<I", 0)  # no next IFD
    header = b"II*\x00" + struct.pack("<I", 8) + ifd
    return header + bytes(DATA_OFFSET - len(header))


def write_float32_tiff(path: str | Path, image: NDArray) -> Path:
    """Write a 2-D image as a float32 TIFF at ``path`` (as given: write to a temporary name for atomicity).

    Parameters
    ----------
    image : array_like, shape (H, W)
        Converted to float32. Files of 4 GiB or more are refused (classic TIFF's offsets are 32-bit).

    Returns
    -------
    Path
    """
    a = np.asarray(image)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"a float32 TIFF needs a non-empty 2-D image, got shape {a.shape}")
    height, width = a.shape
    n_bytes = height * width * 4
    if DATA_OFFSET + n_bytes >= 1 << 32:
        raise ValueError(f"a {width}x{height} float32 image is too large for a classic TIFF")
    header = tiff_header(height, width)

    def fill(buf: mmap.mmap) -> None:
        buf[:DATA_OFFSET] = header
        np.frombuffer(buf, dtype=np.float32, count=height * width, offset=DATA_OFFSET).reshape(height, width)[...] = a

    return write_file(path, DATA_OFFSET + n_bytes, fill)

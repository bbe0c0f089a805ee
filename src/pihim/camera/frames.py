"""Readers for raw DoFP mosaic frames (TIFF, PNG, Lucid ``.raw`` buffers).

:func:`read_frame` reads one raw micro-polarizer mosaic and returns a
:class:`RawFrame` whose ``data`` is a 2-D ``uint8`` or ``uint16`` array with
even, non-zero sides (the Lucid Triton TRI050S-P gives 2448 x 2048, W x H; any
even size is accepted). The reader is chosen by the file extension:

``.tif``, ``.tiff``
    A single-page, single-channel TIFF with 8- or 16-bit unsigned samples,
    decoded with :mod:`tifffile`. Multi-page stacks, RGB and float or signed
    samples are rejected. A ``BitsPerSample`` below the container size (e.g.
    12) is reported as the bit depth.
``.png``
    A single-channel 8- or 16-bit PNG, decoded with OpenCV from the bytes
    read by :func:`numpy.fromfile` (so non-ASCII paths work on every OS).
``.raw``, ``.bin``
    A headerless Lucid Arena pixel buffer, row-major, no line padding. Width
    and height must be given; the pixel format is given or inferred from the
    byte count (see :func:`read_lucid_raw`). Supported formats, with pixel
    ``p0`` first in the buffer and ``b0`` the first byte:

    ``PolarizeMono8``
        One byte per pixel.
    ``PolarizeMono12p`` (GenICam PFNC ``Mono12p``, LSB-first bit packing [1]_)
        Two pixels in three bytes::

            b0 = p0[7:0]
            b1 = p1[3:0] << 4 | p0[11:8]
            b2 = p1[11:4]

    ``PolarizeMono12Packed`` (GigE Vision ``Mono12Packed`` [2]_, [3]_)
        Two pixels in three bytes::

            b0 = p0[11:4]
            b1 = p1[3:0] << 4 | p0[3:0]
            b2 = p1[11:4]

    ``PolarizeMono16``
        Little-endian ``uint16``, two bytes per pixel.

    The 12-bit formats are returned as ``uint16`` with ``bit_depth=12``. A
    buffer of ``1.5 * W * H`` bytes cannot be assigned to one of the two
    12-bit packings without being told which, so the pixel format must then be
    given. Pixel-format names are case-insensitive and the ``Polarize``
    prefix is optional (``mono12p`` is ``PolarizeMono12p``).

Every problem with the input (missing, empty or corrupt file, wrong extension,
size, sample type or channel count, unknown pixel format) raises
:class:`~pihim.errors.PihimInputError` with a one-line message that starts with
the file path, e.g. ``frame.raw: truncated PolarizeMono12p buffer: 100 bytes,
expected 7520256 for 2448x2048``.

References
----------
.. [1] EMVA, "GenICam Pixel Format Naming Convention (PFNC)", version 2.x,
   and "GenICam Pixel Format Values" (GenICamPixelFormatValues.pdf): in the
   ``p`` (lsb) packing of ``Mono12p`` the first byte holds the eight least
   significant bits of the first pixel, the low nibble of the second byte its
   four most significant bits, the high nibble of the second byte the four
   least significant bits of the second pixel and the third byte its eight
   most significant bits.
.. [2] AIA, "GigE Vision Specification", version 2.0, GVSP pixel format
   ``Mono12Packed`` (legacy GigE Vision packing, different from ``Mono12p``).
.. [3] Basler AG, "racer GigE User's Manual" (AW00118302000), section 9.2.3
   "Mono 12 Packed Format": B0 = P0 bits 11..4, B1 = P1 bits 3..0 (high
   nibble) and P0 bits 3..0 (low nibble), B2 = P1 bits 11..4.
.. [4] LUCID Vision Labs, "Triton TRI050S-P/Q Polarized Technical Reference
   Manual", pixel formats ``PolarizeMono8``, ``PolarizeMono12p``,
   ``PolarizeMono12Packed`` and ``PolarizeMono16``.
"""

from __future__ import annotations

import contextlib
import operator
import os
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.layout import check_mosaic_shape
from pihim.errors import PihimInputError

PathLike: TypeAlias = "str | os.PathLike[str]"
BytesLike: TypeAlias = "bytes | bytearray | memoryview | NDArray[np.uint8]"

TIFF_SUFFIXES: tuple[str, ...] = (".tif", ".tiff")
PNG_SUFFIXES: tuple[str, ...] = (".png",)
RAW_SUFFIXES: tuple[str, ...] = (".raw", ".bin")
#: Largest raw value a frame can hold: frames are ``uint8`` or ``uint16`` (a dark or saturation level above it is
#: refused by the commands that read frames).
MAX_RAW_VALUE = 65535

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Largest decoded TIFF accepted, in bytes; guards against corrupt headers
#: that claim gigantic images (a 2448x2048 uint16 frame is 10 MB).
_MAX_DECODED_BYTES = 1 << 30
_BUFFER_LABEL = "<buffer>"


@dataclass(frozen=True)
class RawFrame:
    """A raw mosaic read from disk.

    Attributes
    ----------
    data : numpy.ndarray
        2-D ``uint8`` or ``uint16`` mosaic with even sides.
    bit_depth : int or None
        ADC bits when the file format states it (e.g. 12 for
        PolarizeMono12p), else None (let the pipeline decide).
    pixel_format : str
        What was read, e.g. ``"tiff"``, ``"png"``, ``"PolarizeMono12p"``.
    path : pathlib.Path or None
    """

    data: NDArray[np.uint8] | NDArray[np.uint16]
    bit_depth: int | None
    pixel_format: str
    path: Path | None = None


# -- errors -----------------------------------------------------------------------


def _error(label: str, message: str) -> PihimInputError:
    """A :class:`PihimInputError` reading ``"<label>: <message>"`` on one line."""
    return PihimInputError(" ".join(f"{label}: {message}".splitlines()))


def _describe(exc: BaseException) -> str:
    """Short text for a foreign exception raised while decoding a file."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _os_error(label: str, exc: OSError) -> PihimInputError:
    """Translate an :class:`OSError` raised while opening ``label``."""
    if isinstance(exc, FileNotFoundError):
        return _error(label, "no such file")
    if isinstance(exc, IsADirectoryError):
        return _error(label, "is a directory, not a frame file")
    return _error(label, f"cannot read file: {exc.strerror or _describe(exc)}")


# -- 12-bit packings ------------------------------------------------------------------


def _as_bytes(buf: BytesLike) -> NDArray[np.uint8]:
    """View a bytes-like object or ``uint8`` array as a flat ``uint8`` array."""
    if isinstance(buf, np.ndarray):
        if buf.dtype != np.uint8:
            raise PihimInputError(f"packed buffer must be uint8 bytes, got {buf.dtype}")
        return buf.reshape(-1)
    return np.frombuffer(buf, dtype=np.uint8)


def _packed_groups(buf: BytesLike, width: int, height: int, name: str) -> NDArray[np.uint8]:
    """Reshape a 12-bit packed buffer into ``(width*height/2, 3)`` byte triplets."""
    data = _as_bytes(buf)
    npix = int(width) * int(height)
    if width < 0 or height < 0 or npix % 2:
        raise PihimInputError(f"{name} needs an even number of pixels, got {width}x{height}")
    if data.size != npix // 2 * 3:
        raise PihimInputError(
            f"{name} buffer of {data.size} bytes does not hold {width}x{height} pixels "
            f"(expected {npix // 2 * 3})"
        )
    return data.reshape(-1, 3)


def _pixel_pairs(pixels: ArrayLike, name: str) -> tuple[NDArray[np.uint16], NDArray[np.uint16]]:
    """Validate 12-bit pixels and split them (row-major) into first and second of each pair."""
    arr = np.asarray(pixels)
    if arr.dtype.kind not in "ui":
        raise PihimInputError(f"{name} packs integer pixels, got {arr.dtype}")
    if arr.size % 2:
        raise PihimInputError(f"{name} packs pixel pairs, got an odd count {arr.size}")
    if arr.size and (arr.min() < 0 or arr.max() > 0x0FFF):
        raise PihimInputError(f"{name} packs 12-bit pixels in [0, 4095], got [{arr.min()}, {arr.max()}]")
    flat = arr.reshape(-1).astype(np.uint16)
    return flat[0::2], flat[1::2]


def _interleave(p0: NDArray[np.uint16], p1: NDArray[np.uint16], width: int, height: int) -> NDArray[np.uint16]:
    """Merge first/second pixels of each pair back into a ``(height, width)`` image."""
    out = np.empty((p0.size, 2), dtype=np.uint16)
    out[:, 0] = p0
    out[:, 1] = p1
    return out.reshape(height, width)


def unpack_mono12p(buf: BytesLike, width: int, height: int) -> NDArray[np.uint16]:
    """Unpack a GenICam PFNC ``Mono12p`` buffer (LSB-first 12-bit packing).

    Parameters
    ----------
    buf : bytes-like or numpy.ndarray of uint8
        ``width * height * 3 / 2`` bytes; each byte triplet ``b0 b1 b2``
        holds two pixels ``p0 = b0 | (b1 & 0xF) << 8`` and
        ``p1 = b1 >> 4 | b2 << 4``.
    width, height : int
        Image size in pixels; ``width * height`` must be even.

    Returns
    -------
    numpy.ndarray of uint16, shape (height, width)
        Pixel values in DN, 0..4095.

    Raises
    ------
    PihimInputError
        If the buffer length does not match the size.

    References
    ----------
    EMVA GenICam PFNC, ``Mono12p`` (see the module references).
    """
    g = _packed_groups(buf, width, height, "PolarizeMono12p")
    b0, b1, b2 = (g[:, k].astype(np.uint16) for k in range(3))
    return _interleave(b0 | ((b1 & 0x0F) << 8), (b1 >> 4) | (b2 << 4), width, height)


def unpack_mono12packed(buf: BytesLike, width: int, height: int) -> NDArray[np.uint16]:
    """Unpack a GigE Vision ``Mono12Packed`` buffer.

    Parameters
    ----------
    buf : bytes-like or numpy.ndarray of uint8
        ``width * height * 3 / 2`` bytes; each byte triplet ``b0 b1 b2``
        holds two pixels ``p0 = b0 << 4 | b1 & 0xF`` and
        ``p1 = b2 << 4 | b1 >> 4``.
    width, height : int
        Image size in pixels; ``width * height`` must be even.

    Returns
    -------
    numpy.ndarray of uint16, shape (height, width)
        Pixel values in DN, 0..4095.

    Raises
    ------
    PihimInputError
        If the buffer length does not match the size.

    References
    ----------
    GigE Vision ``Mono12Packed``; Basler racer GigE manual section 9.2.3
    (see the module references).
    """
    g = _packed_groups(buf, width, height, "PolarizeMono12Packed")
    b0, b1, b2 = (g[:, k].astype(np.uint16) for k in range(3))
    return _interleave((b0 << 4) | (b1 & 0x0F), (b2 << 4) | (b1 >> 4), width, height)


def pack_mono12p(pixels: ArrayLike) -> bytes:
    """Pack 12-bit pixels into a GenICam PFNC ``Mono12p`` buffer.

    Inverse of :func:`unpack_mono12p`.

    Parameters
    ----------
    pixels : array_like of int
        Pixel values in DN, 0..4095, taken in row-major order; an even count.

    Returns
    -------
    bytes
        ``1.5`` bytes per pixel.
    """
    p0, p1 = _pixel_pairs(pixels, "PolarizeMono12p")
    out = np.empty((p0.size, 3), dtype=np.uint8)
    out[:, 0] = p0 & 0xFF
    out[:, 1] = ((p1 & 0x0F) << 4) | (p0 >> 8)
    out[:, 2] = p1 >> 4
    return out.tobytes()


def pack_mono12packed(pixels: ArrayLike) -> bytes:
    """Pack 12-bit pixels into a GigE Vision ``Mono12Packed`` buffer.

    Inverse of :func:`unpack_mono12packed`.

    Parameters
    ----------
    pixels : array_like of int
        Pixel values in DN, 0..4095, taken in row-major order; an even count.

    Returns
    -------
    bytes
        ``1.5`` bytes per pixel.
    """
    p0, p1 = _pixel_pairs(pixels, "PolarizeMono12Packed")
    out = np.empty((p0.size, 3), dtype=np.uint8)
    out[:, 0] = p0 >> 4
    out[:, 1] = ((p1 & 0x0F) << 4) | (p0 & 0x0F)
    out[:, 2] = p1 >> 4
    return out.tobytes()


def _unpack_mono8(buf: BytesLike, width: int, height: int) -> NDArray[np.uint8]:
    """One byte per pixel, copied into a writable ``(height, width)`` array."""
    return _as_bytes(buf).reshape(height, width).copy()


def _unpack_mono16(buf: BytesLike, width: int, height: int) -> NDArray[np.uint16]:
    """Little-endian 16-bit pixels as a native-order ``(height, width)`` array."""
    data = np.ascontiguousarray(_as_bytes(buf))
    return data.view("<u2").reshape(height, width).astype(np.uint16)


# -- Lucid pixel formats ------------------------------------------------------------


@dataclass(frozen=True)
class _RawPixelFormat:
    """How one Lucid pixel format is laid out in a headerless buffer."""

    name: str
    bytes_per_pixel_pair: int
    bit_depth: int | None
    unpack: Callable[[BytesLike, int, int], NDArray]

    def nbytes(self, width: int, height: int) -> int:
        """Buffer size in bytes of a ``width`` x ``height`` frame (even pixel count)."""
        return width * height * self.bytes_per_pixel_pair // 2


_FORMATS: dict[str, _RawPixelFormat] = {
    "mono8": _RawPixelFormat("PolarizeMono8", 2, 8, _unpack_mono8),
    "mono12p": _RawPixelFormat("PolarizeMono12p", 3, 12, unpack_mono12p),
    "mono12packed": _RawPixelFormat("PolarizeMono12Packed", 3, 12, unpack_mono12packed),
    "mono16": _RawPixelFormat("PolarizeMono16", 4, None, _unpack_mono16),
}

#: Canonical names of the supported Lucid pixel formats.
PIXEL_FORMATS: tuple[str, ...] = tuple(f.name for f in _FORMATS.values())


def _lookup_format(pixel_format: str) -> _RawPixelFormat:
    """Find a pixel format by name, case-insensitively, ``Polarize`` prefix optional."""
    key = str(pixel_format).strip().lower().removeprefix("polarize")
    if key not in _FORMATS:
        raise PihimInputError(
            f"unknown pixel format {pixel_format!r}; choose one of {', '.join(PIXEL_FORMATS)}"
        )
    return _FORMATS[key]


def normalize_pixel_format(pixel_format: str) -> str:
    """Canonical Lucid name of a pixel format (``"mono12p"`` -> ``"PolarizeMono12p"``).

    Raises
    ------
    PihimInputError
        If the name is not one of :data:`PIXEL_FORMATS` (with or without the
        ``Polarize`` prefix, any case).
    """
    return _lookup_format(pixel_format).name


def _infer_format(label: str, nbytes: int, width: int, height: int) -> _RawPixelFormat:
    """Pick the pixel format from the buffer size when only one fits."""
    npix = width * height
    if nbytes == npix:
        return _FORMATS["mono8"]
    if nbytes == 2 * npix:
        return _FORMATS["mono16"]
    if nbytes == npix // 2 * 3:
        raise _error(
            label,
            f"{nbytes} bytes is 12-bit packed data for {width}x{height}, but PolarizeMono12p "
            "and PolarizeMono12Packed cannot be told apart by size; give the pixel format "
            "(--pixel-format)",
        )
    raise _error(
        label,
        f"{nbytes} bytes does not match {width}x{height} in any pixel format "
        f"(expected {npix} for PolarizeMono8, {npix // 2 * 3} for 12-bit packed or "
        f"{2 * npix} for PolarizeMono16); check --width/--height",
    )


def _check_dimensions(label: str, width: object, height: object) -> tuple[int, int]:
    """Validate the declared frame size of a raw buffer; returns ``(width, height)``."""
    try:
        w, h = operator.index(width), operator.index(height)  # type: ignore[arg-type]
    except TypeError:
        raise _error(label, f"width and height must be integers, got {width!r} and {height!r}") from None
    if w < 0 or h < 0:
        raise _error(label, f"width and height must be positive, got {w}x{h} (WxH)")
    try:
        # Zero-stride view: lets check_mosaic_shape judge the size without allocating.
        shape_probe = np.broadcast_to(np.uint8(0), (h, w))
    except ValueError:
        raise _error(label, f"frame size {w}x{h} (WxH) is too large") from None
    try:
        check_mosaic_shape(shape_probe)
    except PihimInputError as exc:
        raise _error(label, str(exc)) from None
    return w, h


def _read_file_bytes(path: PathLike, label: str) -> NDArray[np.uint8]:
    """All bytes of a regular file as ``uint8`` (:func:`numpy.fromfile`); rejects empty files."""
    _check_file(path, label)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise _os_error(label, exc) from None
    if data.size == 0:
        raise _error(label, "empty file")
    return data


def read_lucid_raw(
    path_or_bytes: PathLike | BytesLike,
    width: int,
    height: int,
    pixel_format: str | None = None,
) -> RawFrame:
    """Read a headerless Lucid pixel buffer.

    Parameters
    ----------
    path_or_bytes : str, os.PathLike, bytes-like or numpy.ndarray of uint8
        A ``.raw``/``.bin`` file, or the buffer itself (error messages then
        start with ``<buffer>``).
    width, height : int
        Frame size in pixels; both even and >= 2.
    pixel_format : str, optional
        ``PolarizeMono8``, ``PolarizeMono12p``, ``PolarizeMono12Packed`` or
        ``PolarizeMono16`` (any case, ``Polarize`` optional). If omitted it is
        inferred from the size: ``W*H`` bytes is Mono8, ``2*W*H`` is Mono16;
        ``1.5*W*H`` is ambiguous and raises.

    Returns
    -------
    RawFrame
        ``uint8`` data with ``bit_depth=8`` for Mono8, ``uint16`` with
        ``bit_depth=12`` for the 12-bit packings, ``uint16`` with
        ``bit_depth=None`` for Mono16.

    Raises
    ------
    PihimInputError
        Missing or empty file, bad size, unknown or ambiguous pixel format,
        truncated or oversized buffer.
    """
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview, np.ndarray)):
        label, path = _BUFFER_LABEL, None
        try:
            data = _as_bytes(path_or_bytes)
        except PihimInputError as exc:
            raise _error(label, str(exc)) from None
        if data.size == 0:
            raise _error(label, "empty buffer")
    else:
        label, path = os.fspath(path_or_bytes), Path(path_or_bytes)
        data = _read_file_bytes(path_or_bytes, label)
    w, h = _check_dimensions(label, width, height)
    if pixel_format is None:
        fmt = _infer_format(label, data.size, w, h)
    else:
        try:
            fmt = _lookup_format(pixel_format)
        except PihimInputError as exc:
            raise _error(label, str(exc)) from None
    expected = fmt.nbytes(w, h)
    if data.size != expected:
        kind = "truncated" if data.size < expected else "oversized"
        raise _error(label, f"{kind} {fmt.name} buffer: {data.size} bytes, expected {expected} for {w}x{h}")
    return RawFrame(fmt.unpack(data, w, h), fmt.bit_depth, fmt.name, path)


# -- image files ----------------------------------------------------------------------


def _checked_mosaic(label: str, data: NDArray) -> NDArray[np.uint8] | NDArray[np.uint16]:
    """Validate a decoded image as a raw mosaic; returns it in native byte order."""
    if data.ndim == 3:
        raise _error(label, f"expected a single-channel image, got {data.shape[2]} channels (shape {data.shape})")
    try:
        check_mosaic_shape(data)
    except PihimInputError as exc:
        raise _error(label, str(exc)) from None
    if data.dtype.kind != "u" or data.dtype.itemsize not in (1, 2):
        raise _error(label, f"unsupported sample type {data.dtype}; expected 8- or 16-bit unsigned integers")
    return data.astype(np.uint8 if data.dtype.itemsize == 1 else np.uint16, copy=False)


def _check_file(path: PathLike, label: str) -> None:
    """Raise unless ``path`` is an existing, non-empty regular file (a FIFO would block the reader)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _os_error(label, exc) from None
    if stat.S_ISDIR(st.st_mode):
        raise _error(label, "is a directory, not a frame file")
    if not stat.S_ISREG(st.st_mode):
        raise _error(label, "not a regular file (a FIFO, device or socket); give a frame file")
    if st.st_size == 0:
        raise _error(label, "empty file")


def _decode_tiff(label: str, path: PathLike) -> tuple[NDArray, int]:
    """Decode the only page of a TIFF; returns the samples and ``BitsPerSample``."""
    import tifffile  # here: a command's --help need not load it

    with tifffile.TiffFile(path) as tif:
        npages = len(tif.pages)
        if npages != 1:
            raise _error(label, f"TIFF has {npages} pages; expected a single 2-D page")
        page = tif.pages[0]
        dtype = page.dtype
        if dtype is None or dtype.kind != "u" or dtype.itemsize not in (1, 2):
            raise _error(label, f"unsupported sample type {dtype}; expected 8- or 16-bit unsigned integers")
        if len(page.shape) != 2:
            raise _error(label, f"expected a single-channel 2-D TIFF page, got shape {page.shape}")
        if int(np.prod(page.shape, dtype=np.float64)) * dtype.itemsize > _MAX_DECODED_BYTES:
            raise _error(label, f"TIFF page of shape {page.shape} is too large")
        return page.asarray(), int(page.bitspersample)


def read_tiff(path: PathLike) -> RawFrame:
    """Read a single-page, single-channel 8- or 16-bit TIFF mosaic.

    Parameters
    ----------
    path : str or os.PathLike
        The TIFF file.

    Returns
    -------
    RawFrame
        ``pixel_format="tiff"``; ``bit_depth`` is 8 for ``uint8`` data, the
        TIFF ``BitsPerSample`` when it is below 16 for ``uint16`` data (e.g.
        12), else None.

    Raises
    ------
    PihimInputError
        Missing, empty or corrupt file, several pages, several channels,
        non-``uint8``/``uint16`` samples or odd sides.
    """
    label = os.fspath(path)
    _check_file(path, label)
    try:
        data, bits = _decode_tiff(label, path)
    except PihimInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile raises many types on corrupt files
        raise _error(label, f"cannot read TIFF: {_describe(exc)}") from None
    data = _checked_mosaic(label, data)
    container = 8 * data.dtype.itemsize
    bit_depth = bits if 0 < bits < container else (8 if container == 8 else None)
    return RawFrame(data, bit_depth, "tiff", Path(path))


@contextlib.contextmanager
def stderr_captured(lines: list[str]) -> Iterator[None]:
    """Send what C libraries write to file descriptor 2 into ``lines`` instead of the terminal.

    Decoders such as libpng print their own error lines on stderr; pihim
    reports the failure once, in its own message. Where descriptor 2 cannot
    be redirected, nothing is captured.
    """
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    with tempfile.TemporaryFile() as sink:
        try:
            sys.stderr.flush()
            os.dup2(sink.fileno(), 2)
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(sink.read(4096).decode("utf-8", "replace").splitlines())


def _check_png_chunks(label: str, raw: NDArray[np.uint8]) -> None:
    """Walk the PNG chunk list up to ``IEND``; reject lengths running past the file end.

    A corrupt chunk length can make the decoder spend seconds before failing,
    so truncated or corrupt files are caught here first.
    """
    view = memoryview(raw)
    pos = len(_PNG_SIGNATURE)
    while pos + 8 <= len(view):
        length = int.from_bytes(view[pos : pos + 4], "big")
        kind = bytes(view[pos + 4 : pos + 8]).decode("ascii", "backslashreplace")
        pos += 12 + length  # length, type, data, CRC
        if pos > len(view):
            raise _error(label, f"truncated or corrupt PNG: {kind!r} chunk of {length} bytes runs past the end of the file")
        if kind == "IEND":
            return
    raise _error(label, "truncated PNG: no IEND chunk")


def read_png(path: PathLike) -> RawFrame:
    """Read a single-channel 8- or 16-bit PNG mosaic.

    The file is read with :func:`numpy.fromfile` and decoded with
    :func:`cv2.imdecode` (``IMREAD_UNCHANGED``), so non-ASCII paths work.

    Parameters
    ----------
    path : str or os.PathLike
        The PNG file.

    Returns
    -------
    RawFrame
        ``pixel_format="png"``; ``bit_depth`` 8 for 8-bit data, None for
        16-bit data.

    Raises
    ------
    PihimInputError
        Missing, empty, corrupt or non-PNG file, colour or grey+alpha image,
        or odd sides.
    """
    label = os.fspath(path)
    raw = _read_file_bytes(path, label)
    if raw[: len(_PNG_SIGNATURE)].tobytes() != _PNG_SIGNATURE:
        raise _error(label, "not a PNG file (bad signature)")
    _check_png_chunks(label, raw)
    import cv2  # here: OpenCV's import is about 0.1 s of CPU that a command's --help need not pay

    # OpenCV logs its own warning line for corrupt buffers; the error below says it all
    log_level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    captured: list[str] = []
    try:
        with stderr_captured(captured):  # libpng prints "libpng error: ..." itself
            img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    except Exception as exc:  # noqa: BLE001 - cv2.error (or MemoryError) on corrupt data
        raise _error(label, f"cannot decode PNG: {_describe(exc)}") from None
    finally:
        cv2.utils.logging.setLogLevel(log_level)
    if img is None:
        detail = "; ".join(line.strip() for line in captured if line.strip())
        raise _error(label, f"cannot decode PNG ({detail or 'corrupt or unsupported file'})")
    data = _checked_mosaic(label, img)
    return RawFrame(data, 8 if data.dtype == np.uint8 else None, "png", Path(path))


# -- entry point ------------------------------------------------------------------------


def _check_declared_size(label: str, data: NDArray, width: int | None, height: int | None) -> None:
    """If a size was given for an image file, it must match the image."""
    h, w = data.shape
    if (width is not None and width != w) or (height is not None and height != h):
        raise _error(
            label,
            f"image is {w}x{h} (WxH) but {width if width is not None else w}x"
            f"{height if height is not None else h} was given",
        )


def read_frame(
    path: str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    pixel_format: str | None = None,
) -> RawFrame:
    """Read one raw mosaic frame; raises PihimInputError on any bad input.

    Parameters
    ----------
    path : str or pathlib.Path
        ``.tif``/``.tiff``, ``.png`` or ``.raw``/``.bin`` file (extension
        case-insensitive).
    width, height : int, optional
        Frame size in pixels. Required for ``.raw``/``.bin``; for TIFF and
        PNG, if given, they must match the image.
    pixel_format : str, optional
        Lucid pixel format of a ``.raw``/``.bin`` buffer (see
        :func:`read_lucid_raw`); inferred from the size when unambiguous.
        Not allowed for TIFF and PNG.

    Returns
    -------
    RawFrame
        2-D ``uint8`` or ``uint16`` mosaic with even sides.

    Raises
    ------
    PihimInputError
        For every unreadable or unsuitable input; the one-line message starts
        with ``path``.
    """
    label = os.fspath(path)
    if Path(path).is_dir():
        raise _error(label, "is a directory, not a frame file (give the frame files, e.g. DIR/*.tiff)")
    suffix = Path(path).suffix.lower()
    if suffix in RAW_SUFFIXES:
        if width is None or height is None:
            raise _error(label, "width and height are required for a raw buffer (--width, --height)")
        return read_lucid_raw(path, width, height, pixel_format)
    if suffix in TIFF_SUFFIXES or suffix in PNG_SUFFIXES:
        if pixel_format is not None:
            raise _error(label, "a pixel format applies only to .raw/.bin buffers, not to TIFF or PNG")
        frame = read_tiff(path) if suffix in TIFF_SUFFIXES else read_png(path)
        _check_declared_size(label, frame.data, width, height)
        return frame
    known = ", ".join(TIFF_SUFFIXES + PNG_SUFFIXES + RAW_SUFFIXES)
    raise _error(label, f"unsupported file type {suffix or '(no extension)'!r}; expected one of {known}")

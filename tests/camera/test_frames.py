"""Tests of the raw-frame readers (TIFF, PNG and Lucid ``.raw`` buffers)."""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pihim.camera.frames import (
    PIXEL_FORMATS,
    RawFrame,
    normalize_pixel_format,
    pack_mono12p,
    pack_mono12packed,
    read_frame,
    read_lucid_raw,
    read_png,
    read_tiff,
    unpack_mono12p,
    unpack_mono12packed,
)
from pihim.errors import PihimInputError

LUCID_W, LUCID_H = 2448, 2048
HYPOTHESIS = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)


# -- helpers --------------------------------------------------------------------------


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _write_png(path: Path, image: np.ndarray) -> None:
    """PNG via cv2.imencode so that non-ASCII paths work too."""
    ok, buf = cv2.imencode(".png", image)
    assert ok
    path.write_bytes(buf.tobytes())


def _assert_input_error(call: Callable[[], object], path: object, *fragments: str) -> PihimInputError:
    """``call`` raises PihimInputError with a one-line message starting with ``path``."""
    with pytest.raises(PihimInputError) as info:
        call()
    message = str(info.value)
    assert message.startswith(f"{os.fspath(path)}: "), message
    assert len(message.splitlines()) == 1 and "\n" not in message and "\r" not in message, message
    for fragment in fragments:
        assert fragment.lower() in message.lower(), message
    return info.value


def _valid_frame_or_input_error(call: Callable[[], RawFrame], path: object) -> RawFrame | None:
    """The fuzzing oracle: a valid RawFrame, or a well-formed PihimInputError."""
    try:
        frame = call()
    except PihimInputError as exc:
        message = str(exc)
        assert message.startswith(f"{os.fspath(path)}: "), message
        assert len(message.splitlines()) == 1, message
        return None
    assert isinstance(frame, RawFrame)
    data = frame.data
    assert isinstance(data, np.ndarray)
    assert data.ndim == 2
    h, w = data.shape
    assert h >= 2 and w >= 2 and h % 2 == 0 and w % 2 == 0
    assert data.dtype in (np.dtype(np.uint8), np.dtype(np.uint16))
    assert data.dtype.isnative
    if frame.bit_depth is not None:
        assert 1 <= frame.bit_depth <= 8 * data.dtype.itemsize
        assert int(data.max()) < 2**frame.bit_depth
    return frame


# -- TIFF and PNG round trips ---------------------------------------------------------------


@pytest.mark.parametrize(("dtype", "bit_depth"), [(np.uint8, 8), (np.uint16, None)])
def test_tiff_round_trip(tmp_path: Path, dtype: type, bit_depth: int | None) -> None:
    info = np.iinfo(dtype)
    image = _rng(1).integers(0, info.max, size=(6, 10), endpoint=True, dtype=dtype)
    path = tmp_path / "frame.tif"
    tifffile.imwrite(path, image)
    frame = read_frame(path)
    assert frame.data.dtype == dtype
    np.testing.assert_array_equal(frame.data, image)
    assert frame.pixel_format == "tiff"
    assert frame.bit_depth == bit_depth
    assert frame.path == path


def test_tiff_full_sensor_size_and_uppercase_extension(tmp_path: Path) -> None:
    image = _rng(2).integers(0, 4095, size=(LUCID_H, LUCID_W), endpoint=True, dtype=np.uint16)
    path = tmp_path / "FRAME.TIFF"
    tifffile.imwrite(path, image)
    frame = read_frame(str(path))
    assert frame.data.shape == (LUCID_H, LUCID_W)
    np.testing.assert_array_equal(frame.data, image)


def test_big_endian_tiff_returns_native_uint16(tmp_path: Path) -> None:
    image = np.arange(16, dtype=np.uint16).reshape(4, 4) * 4000
    path = tmp_path / "big_endian.tif"
    tifffile.imwrite(path, image, byteorder=">")
    frame = read_tiff(path)
    assert frame.data.dtype == np.dtype(np.uint16) and frame.data.dtype.isnative
    np.testing.assert_array_equal(frame.data, image)


@pytest.mark.parametrize(("dtype", "bit_depth"), [(np.uint8, 8), (np.uint16, None)])
def test_png_round_trip(tmp_path: Path, dtype: type, bit_depth: int | None) -> None:
    info = np.iinfo(dtype)
    image = _rng(3).integers(0, info.max, size=(8, 12), endpoint=True, dtype=dtype)
    path = tmp_path / "frame.png"
    assert cv2.imwrite(str(path), image)
    frame = read_frame(path)
    assert frame.data.dtype == dtype
    np.testing.assert_array_equal(frame.data, image)
    assert frame.pixel_format == "png"
    assert frame.bit_depth == bit_depth


def test_non_ascii_paths(tmp_path: Path) -> None:
    folder = tmp_path / "héliostat_偏振"
    folder.mkdir()
    image = _rng(4).integers(0, 65535, size=(4, 6), endpoint=True, dtype=np.uint16)
    _write_png(folder / "帧 1.png", image)
    tifffile.imwrite(folder / "帧 1.tif", image)
    (folder / "帧 1.raw").write_bytes(image.astype("<u2").tobytes())
    np.testing.assert_array_equal(read_frame(folder / "帧 1.png").data, image)
    np.testing.assert_array_equal(read_frame(folder / "帧 1.tif").data, image)
    raw = read_frame(folder / "帧 1.raw", width=6, height=4, pixel_format="Mono16")
    np.testing.assert_array_equal(raw.data, image)


def test_declared_size_must_match_image(tmp_path: Path) -> None:
    path = tmp_path / "frame.png"
    _write_png(path, np.zeros((4, 6), np.uint8))
    assert read_frame(path, width=6, height=4).data.shape == (4, 6)
    _assert_input_error(lambda: read_frame(path, width=4, height=6), path, "6x4")


# -- 12-bit packings ------------------------------------------------------------------------


def test_mono12p_hand_computed_bytes() -> None:
    # PFNC Mono12p: b0 = p0[7:0], b1 = p1[3:0] << 4 | p0[11:8], b2 = p1[11:4]
    assert pack_mono12p([0xABC, 0x123]) == bytes([0xBC, 0x3A, 0x12])
    assert pack_mono12p([0x001, 0xF00]) == bytes([0x01, 0x00, 0xF0])
    assert pack_mono12p([0xF00, 0x00F]) == bytes([0x00, 0xFF, 0x00])
    np.testing.assert_array_equal(unpack_mono12p(bytes([0xBC, 0x3A, 0x12]), 2, 1), [[0xABC, 0x123]])


def test_mono12packed_hand_computed_bytes() -> None:
    # GigE Vision Mono12Packed: b0 = p0[11:4], b1 = p1[3:0] << 4 | p0[3:0], b2 = p1[11:4]
    assert pack_mono12packed([0xABC, 0x123]) == bytes([0xAB, 0x3C, 0x12])
    assert pack_mono12packed([0x001, 0xF00]) == bytes([0x00, 0x01, 0xF0])
    assert pack_mono12packed([0xF00, 0x00F]) == bytes([0xF0, 0xF0, 0x00])
    np.testing.assert_array_equal(unpack_mono12packed(bytes([0xAB, 0x3C, 0x12]), 2, 1), [[0xABC, 0x123]])


def test_raw_file_hand_computed_2x2(tmp_path: Path) -> None:
    # Row-major pixels 0xABC 0x123 / 0x456 0xFED in both packings.
    expected = np.array([[0xABC, 0x123], [0x456, 0xFED]], dtype=np.uint16)
    cases = {
        "PolarizeMono12p": bytes([0xBC, 0x3A, 0x12, 0x56, 0xD4, 0xFE]),
        "PolarizeMono12Packed": bytes([0xAB, 0x3C, 0x12, 0x45, 0xD6, 0xFE]),
    }
    for name, payload in cases.items():
        path = tmp_path / f"{name}.raw"
        path.write_bytes(payload)
        frame = read_frame(path, width=2, height=2, pixel_format=name)
        assert frame.data.dtype == np.uint16
        np.testing.assert_array_equal(frame.data, expected)
        assert frame.bit_depth == 12
        assert frame.pixel_format == name


@pytest.mark.parametrize(
    ("pack", "unpack"),
    [(pack_mono12p, unpack_mono12p), (pack_mono12packed, unpack_mono12packed)],
)
def test_12bit_round_trip_random(pack: Callable, unpack: Callable) -> None:
    pixels = _rng(5).integers(0, 4095, size=(64, 98), endpoint=True, dtype=np.uint16)
    packed = pack(pixels)
    assert len(packed) == pixels.size * 3 // 2
    out = unpack(packed, 98, 64)
    assert out.dtype == np.uint16 and out.shape == (64, 98)
    np.testing.assert_array_equal(out, pixels)
    # also from a uint8 array and a bytearray
    np.testing.assert_array_equal(unpack(np.frombuffer(packed, np.uint8), 98, 64), pixels)
    np.testing.assert_array_equal(unpack(bytearray(packed), 98, 64), pixels)


def test_the_two_12bit_packings_differ() -> None:
    pixels = _rng(6).integers(0, 4095, size=(4, 8), endpoint=True, dtype=np.uint16)
    assert pack_mono12p(pixels) != pack_mono12packed(pixels)
    assert not np.array_equal(unpack_mono12packed(pack_mono12p(pixels), 8, 4), pixels)


def test_full_size_mono12p_frame(tmp_path: Path) -> None:
    pixels = _rng(7).integers(0, 4095, size=(LUCID_H, LUCID_W), endpoint=True, dtype=np.uint16)
    path = tmp_path / "frame.raw"
    path.write_bytes(pack_mono12p(pixels))
    frame = read_frame(path, width=LUCID_W, height=LUCID_H, pixel_format="PolarizeMono12p")
    np.testing.assert_array_equal(frame.data, pixels)
    assert (frame.bit_depth, frame.pixel_format, frame.path) == (12, "PolarizeMono12p", path)


@pytest.mark.parametrize("bad", [[0, 4096], [-1, 0], [1, 2, 3], np.array([0.0, 1.0])])
def test_pack_rejects_bad_pixels(bad: object) -> None:
    for pack in (pack_mono12p, pack_mono12packed):
        with pytest.raises(PihimInputError):
            pack(bad)


def test_unpack_rejects_wrong_length() -> None:
    for unpack in (unpack_mono12p, unpack_mono12packed):
        with pytest.raises(PihimInputError):
            unpack(b"\x00" * 5, 2, 2)
        with pytest.raises(PihimInputError):
            unpack(b"\x00" * 7, 2, 2)


# -- Mono8 / Mono16 and pixel-format names -------------------------------------------------------


def test_mono16_is_little_endian(tmp_path: Path) -> None:
    path = tmp_path / "frame.bin"
    path.write_bytes(bytes([0x34, 0x12, 0xFF, 0x00, 0x00, 0xFF, 0x01, 0x80]))
    frame = read_frame(path, width=2, height=2, pixel_format="PolarizeMono16")
    assert frame.data.dtype == np.dtype(np.uint16) and frame.data.dtype.isnative
    np.testing.assert_array_equal(frame.data, [[0x1234, 0x00FF], [0xFF00, 0x8001]])
    assert frame.bit_depth is None
    assert frame.pixel_format == "PolarizeMono16"


def test_mono8(tmp_path: Path) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(range(8)))
    frame = read_frame(path, width=4, height=2, pixel_format="mono8")
    assert frame.data.dtype == np.uint8
    np.testing.assert_array_equal(frame.data, [[0, 1, 2, 3], [4, 5, 6, 7]])
    assert (frame.bit_depth, frame.pixel_format) == (8, "PolarizeMono8")
    frame.data[0, 0] = 9  # writable, not a view of an immutable buffer


@pytest.mark.parametrize(
    ("alias", "canonical"),
    [
        ("Mono12p", "PolarizeMono12p"),
        ("MONO12P", "PolarizeMono12p"),
        ("polarizemono12p", "PolarizeMono12p"),
        (" PolarizeMono12p ", "PolarizeMono12p"),
        ("mono12packed", "PolarizeMono12Packed"),
        ("POLARIZEMONO12PACKED", "PolarizeMono12Packed"),
        ("Mono8", "PolarizeMono8"),
        ("polarizeMono16", "PolarizeMono16"),
    ],
)
def test_pixel_format_aliases(alias: str, canonical: str) -> None:
    assert normalize_pixel_format(alias) == canonical
    assert canonical in PIXEL_FORMATS


def test_pixel_format_inferred_from_size(tmp_path: Path) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(16))
    assert read_frame(path, width=4, height=4).pixel_format == "PolarizeMono8"
    path.write_bytes(bytes(32))
    assert read_frame(path, width=4, height=4).pixel_format == "PolarizeMono16"
    path.write_bytes(bytes(24))
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "--pixel-format")
    path.write_bytes(bytes(20))
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "20 bytes")


def test_read_lucid_raw_from_bytes() -> None:
    frame = read_lucid_raw(pack_mono12packed([1, 2, 3, 4]), 2, 2, "Mono12Packed")
    np.testing.assert_array_equal(frame.data, [[1, 2], [3, 4]])
    assert frame.path is None
    _assert_input_error(lambda: read_lucid_raw(b"\x00" * 5, 2, 2, "mono8"), "<buffer>", "oversized")


# -- bad input -----------------------------------------------------------------------------------


def test_truncated_raw_message_matches_spec(tmp_path: Path) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(100))
    err = _assert_input_error(
        lambda: read_frame(path, width=LUCID_W, height=LUCID_H, pixel_format="Mono12p"), path
    )
    assert str(err) == f"{path}: truncated PolarizeMono12p buffer: 100 bytes, expected 7520256 for 2448x2048"


@pytest.mark.parametrize("fmt", PIXEL_FORMATS)
@pytest.mark.parametrize(("delta", "word"), [(-1, "truncated"), (+1, "oversized"), (+3, "oversized")])
def test_truncated_or_oversized_raw(tmp_path: Path, fmt: str, delta: int, word: str) -> None:
    bytes_per_pair = {"PolarizeMono8": 2, "PolarizeMono12p": 3, "PolarizeMono12Packed": 3, "PolarizeMono16": 4}
    size = 6 * 4 // 2 * bytes_per_pair[fmt] + delta
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(size))
    _assert_input_error(lambda: read_frame(path, width=6, height=4, pixel_format=fmt), path, word, fmt)


@pytest.mark.parametrize(("width", "height"), [(3, 4), (4, 3), (0, 4), (4, 0), (-2, 4)])
def test_raw_bad_sides(tmp_path: Path, width: int, height: int) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(24))
    _assert_input_error(lambda: read_frame(path, width=width, height=height, pixel_format="mono8"), path)


def test_raw_requires_width_and_height(tmp_path: Path) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(16))
    _assert_input_error(lambda: read_frame(path), path, "width")
    _assert_input_error(lambda: read_frame(path, width=4), path, "height")
    _assert_input_error(lambda: read_frame(path, width=4.0, height=4), path, "integer")  # type: ignore[arg-type]


def test_unknown_pixel_format(tmp_path: Path) -> None:
    path = tmp_path / "frame.raw"
    path.write_bytes(bytes(16))
    _assert_input_error(lambda: read_frame(path, width=4, height=4, pixel_format="Mono10p"), path, "Mono10p")
    with pytest.raises(PihimInputError):
        normalize_pixel_format("BayerRG8")


def test_pixel_format_not_allowed_for_images(tmp_path: Path) -> None:
    path = tmp_path / "frame.tif"
    tifffile.imwrite(path, np.zeros((4, 4), np.uint8))
    _assert_input_error(lambda: read_frame(path, pixel_format="mono8"), path)


@pytest.mark.parametrize("name", ["frame.jpg", "frame", "frame.tif.gz", "frame.npy"])
def test_unsupported_extension(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(bytes(16))
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "unsupported")


@pytest.mark.parametrize("name", ["missing.tif", "missing.png", "missing.raw"])
def test_missing_file(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "no such file")


@pytest.mark.parametrize("name", ["empty.tiff", "empty.png", "empty.bin"])
def test_empty_file(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.touch()
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "empty")


@pytest.mark.parametrize("name", ["folder.tif", "folder.png", "folder.raw"])
def test_directory(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.mkdir()
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "directory")


def test_odd_sided_images(tmp_path: Path) -> None:
    tif, png = tmp_path / "odd.tif", tmp_path / "odd.png"
    tifffile.imwrite(tif, np.zeros((4, 5), np.uint16))
    _write_png(png, np.zeros((3, 4), np.uint8))
    _assert_input_error(lambda: read_frame(tif), tif, "even")
    _assert_input_error(lambda: read_frame(png), png, "even")


def test_colour_images(tmp_path: Path) -> None:
    rgb = _rng(8).integers(0, 255, size=(4, 4, 3), endpoint=True, dtype=np.uint8)
    tif, png, rgba = tmp_path / "rgb.tif", tmp_path / "rgb.png", tmp_path / "rgba.png"
    tifffile.imwrite(tif, rgb, photometric="rgb")
    _write_png(png, rgb)
    _write_png(rgba, np.dstack([rgb, rgb[..., :1]]))
    for path in (tif, png, rgba):
        _assert_input_error(lambda path=path: read_frame(path), path)


def test_multi_page_tiff(tmp_path: Path) -> None:
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, np.zeros((3, 4, 6), np.uint16), photometric="minisblack")
    _assert_input_error(lambda: read_frame(stack), stack, "3 pages")
    appended = tmp_path / "appended.tif"
    tifffile.imwrite(appended, np.zeros((4, 4), np.uint8))
    tifffile.imwrite(appended, np.zeros((4, 4), np.uint8), append=True)
    _assert_input_error(lambda: read_frame(appended), appended, "2 pages")


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32, np.int16, np.int8, np.uint32])
def test_tiff_wrong_dtype(tmp_path: Path, dtype: type) -> None:
    path = tmp_path / "frame.tif"
    tifffile.imwrite(path, np.ones((4, 4), dtype))
    _assert_input_error(lambda: read_frame(path), path, "sample type")


def test_corrupt_and_non_image_files(tmp_path: Path) -> None:
    good_tif = io.BytesIO()
    tifffile.imwrite(good_tif, np.arange(64, dtype=np.uint16).reshape(8, 8))
    ok, good_png = cv2.imencode(".png", np.arange(64, dtype=np.uint8).reshape(8, 8))
    assert ok
    cases = {
        "text.tif": b"this is not an image\n",
        "text.png": b"this is not an image\n",
        "truncated.tif": good_tif.getvalue()[:40],
        "truncated.png": good_png.tobytes()[:30],
        "garbage_after_signature.png": b"\x89PNG\r\n\x1a\n" + bytes(range(256)),
        "garbage_after_magic.tif": b"II*\x00" + bytes(range(200)),
        "jpeg_named.png": cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes(),
        "png_named.tif": good_png.tobytes(),
    }
    for name, payload in cases.items():
        path = tmp_path / name
        path.write_bytes(payload)
        _assert_input_error(lambda path=path: read_frame(path), path)


def test_png_with_corrupt_chunk_length_fails_fast(tmp_path: Path) -> None:
    ok, encoded = cv2.imencode(".png", np.zeros((8, 8), np.uint16))
    assert ok
    payload = bytearray(encoded.tobytes())
    idat = payload.index(b"IDAT") - 4
    payload[idat : idat + 4] = (0xF0000000).to_bytes(4, "big")  # absurd IDAT length
    path = tmp_path / "frame.png"
    path.write_bytes(bytes(payload))
    _assert_input_error(lambda: read_png(path), path, "runs past the end")
    path.write_bytes(encoded.tobytes()[:-12])  # IEND chunk cut off
    _assert_input_error(lambda: read_png(path), path, "no IEND")


# -- property tests -------------------------------------------------------------------------------

_RAW_FORMATS = st.sampled_from([None, *PIXEL_FORMATS, "mono12p", "MONO16", "Mono10p", "", "rgb8"])


@HYPOTHESIS
@given(
    payload=st.binary(min_size=0, max_size=300),
    width=st.integers(-2, 14),
    height=st.integers(-2, 14),
    pixel_format=_RAW_FORMATS,
    suffix=st.sampled_from([".raw", ".bin", ".RAW"]),
)
def test_fuzz_raw_buffers(
    tmp_path_factory: pytest.TempPathFactory,
    payload: bytes,
    width: int,
    height: int,
    pixel_format: str | None,
    suffix: str,
) -> None:
    path = tmp_path_factory.mktemp("raw") / f"frame{suffix}"
    path.write_bytes(payload)
    frame = _valid_frame_or_input_error(
        lambda: read_frame(path, width=width, height=height, pixel_format=pixel_format), path
    )
    if frame is not None:
        assert frame.data.shape == (height, width)


@HYPOTHESIS
@given(width=st.integers(1, 12).map(lambda n: 2 * n), height=st.integers(1, 12).map(lambda n: 2 * n), data=st.data())
def test_fuzz_raw_round_trip(width: int, height: int, data: st.DataObject) -> None:
    fmt = data.draw(st.sampled_from(PIXEL_FORMATS))
    pixels = data.draw(
        hnp.arrays(
            np.uint16,
            (height, width),
            elements=st.integers(0, {"PolarizeMono8": 255, "PolarizeMono16": 65535}.get(fmt, 4095)),
        )
    )
    payload = {
        "PolarizeMono8": lambda: pixels.astype(np.uint8).tobytes(),
        "PolarizeMono12p": lambda: pack_mono12p(pixels),
        "PolarizeMono12Packed": lambda: pack_mono12packed(pixels),
        "PolarizeMono16": lambda: pixels.astype("<u2").tobytes(),
    }[fmt]()
    frame = read_lucid_raw(payload, width, height, fmt.lower().removeprefix("polarize"))
    assert frame.pixel_format == fmt
    np.testing.assert_array_equal(frame.data, pixels)


_IMAGE_DTYPES = st.sampled_from([np.uint8, np.uint16, np.int16, np.int32, np.float32, np.float64])


@HYPOTHESIS
@given(
    image=_IMAGE_DTYPES.flatmap(
        lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=2, max_dims=3, min_side=1, max_side=7))
    ),
    as_rgb=st.booleans(),
)
def test_fuzz_tiff_arrays(tmp_path_factory: pytest.TempPathFactory, image: np.ndarray, as_rgb: bool) -> None:
    path = tmp_path_factory.mktemp("tif") / "frame.tif"
    rgb = as_rgb and image.ndim == 3 and image.shape[-1] in (3, 4)
    # minisblack writes a 3-D array as a stack of pages; rgb as one colour page
    tifffile.imwrite(path, image, photometric="rgb" if rgb else "minisblack")
    frame = _valid_frame_or_input_error(lambda: read_frame(path), path)
    acceptable = (
        image.ndim == 2
        and image.dtype in (np.dtype(np.uint8), np.dtype(np.uint16))
        and image.shape[0] % 2 == 0
        and image.shape[1] % 2 == 0
    )
    if acceptable:
        assert frame is not None
        np.testing.assert_array_equal(frame.data, image)
    if frame is not None:
        assert frame.data.size == image.size
        np.testing.assert_array_equal(frame.data.ravel(), image.ravel())


@HYPOTHESIS
@given(
    image=st.sampled_from([np.uint8, np.uint16]).flatmap(
        lambda dt: st.tuples(
            st.integers(1, 7), st.integers(1, 7), st.sampled_from([None, 1, 3, 4])
        ).flatmap(lambda s: hnp.arrays(dt, s[:2] if s[2] is None else s))
    )
)
def test_fuzz_png_arrays(tmp_path_factory: pytest.TempPathFactory, image: np.ndarray) -> None:
    path = tmp_path_factory.mktemp("png") / "frame.png"
    _write_png(path, image)
    frame = _valid_frame_or_input_error(lambda: read_frame(path), path)
    single_channel = image.ndim == 2 or image.shape[2] == 1
    even = image.shape[0] % 2 == 0 and image.shape[1] % 2 == 0
    assert (frame is not None) == (single_channel and even)
    if frame is not None:
        np.testing.assert_array_equal(frame.data, image.reshape(image.shape[:2]))


@HYPOTHESIS
@given(payload=st.binary(max_size=400), suffix=st.sampled_from([".tif", ".tiff", ".png"]))
def test_fuzz_random_bytes_as_images(
    tmp_path_factory: pytest.TempPathFactory, payload: bytes, suffix: str
) -> None:
    path = tmp_path_factory.mktemp("img") / f"frame{suffix}"
    path.write_bytes(payload)
    _valid_frame_or_input_error(lambda: read_frame(path), path)


def _valid_image_bytes() -> dict[str, bytes]:
    image = np.arange(48, dtype=np.uint16).reshape(6, 8) * 1000
    tif = io.BytesIO()
    tifffile.imwrite(tif, image)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return {".tif": tif.getvalue(), ".png": png.tobytes()}


_VALID_IMAGES = _valid_image_bytes()


@HYPOTHESIS
@given(
    suffix=st.sampled_from(sorted(_VALID_IMAGES)),
    edits=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=6),
    keep=st.none() | st.floats(0.0, 1.0),
)
def test_fuzz_corrupted_valid_images(
    tmp_path_factory: pytest.TempPathFactory, suffix: str, edits: list[tuple[int, int]], keep: float | None
) -> None:
    """Overwrite a few bytes of a valid file and/or cut it short."""
    payload = bytearray(_VALID_IMAGES[suffix])
    for position, value in edits:
        payload[position % len(payload)] = value
    if keep is not None:
        payload = payload[: int(keep * len(payload))]
    path = tmp_path_factory.mktemp("corrupt") / f"frame{suffix}"
    path.write_bytes(bytes(payload))
    _valid_frame_or_input_error(lambda: read_frame(path), path)


@pytest.mark.parametrize("name", ["x.raw", "x.tiff", "x.png"])
def test_fifo_refused_without_blocking(tmp_path: Path, name: str) -> None:
    # issue 10: a FIFO named x.raw made the reader block forever
    path = tmp_path / name
    os.mkfifo(path)
    _assert_input_error(lambda: read_frame(path, width=4, height=4), path, "not a regular file")


def test_corrupt_png_libpng_text_in_one_message(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    # issue 10: libpng printed its own 'libpng error:' line beside pihim's message
    ok, buf = cv2.imencode(".png", (np.arange(64 * 64).reshape(64, 64) % 4096).astype(np.uint16))
    data = bytearray(buf.tobytes())
    i = data.index(b"IDAT")
    data[i + 10 : i + 30] = bytes(20)
    path = tmp_path / "bad.png"
    path.write_bytes(bytes(data))
    with pytest.raises(PihimInputError) as err:
        read_frame(path)
    assert str(path) in str(err.value) and "libpng" in str(err.value)
    assert capfd.readouterr().err == ""

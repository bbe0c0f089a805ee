"""The output writers of ``pihim polar``: float32 TIFFs (``pihim._tiff``, read back by tifffile and OpenCV) and
files written past the page cache (``pihim._direct_io``)."""

import errno
import os

import cv2
import numpy as np
import pytest
import tifffile

from pihim import _direct_io, _tiff


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (37, 1001), (1024, 1224)])
def test_readers_get_the_image_back(tmp_path, shape):
    rng = np.random.default_rng(sum(shape))
    image = rng.normal(1000, 300, shape).astype(np.float32)
    image.flat[::7] = np.nan
    image.flat[1::11] = -np.inf
    path = _tiff.write_float32_tiff(tmp_path / "x.tiff", image)
    assert path.stat().st_size == _tiff.DATA_OFFSET + image.nbytes  # cut back after whole-block direct writes
    with tifffile.TiffFile(path) as tif:
        assert len(tif.pages) == 1
        back = tif.asarray()
    assert back.dtype == np.float32 and np.array_equal(back, image, equal_nan=True)
    seen = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # libtiff
    assert seen.dtype == np.float32 and np.array_equal(seen, image, equal_nan=True)


def test_float64_input_and_bad_shapes(tmp_path):
    x = np.linspace(0, 1, 12).reshape(3, 4)
    back = tifffile.imread(_tiff.write_float32_tiff(tmp_path / "x.tiff", x))
    assert np.array_equal(back, x.astype(np.float32))
    for bad in (np.zeros(5), np.zeros((0, 4)), np.zeros((2, 2, 2))):
        with pytest.raises(ValueError, match="2-D"):
            _tiff.write_float32_tiff(tmp_path / "y.tiff", bad)


def test_page_cache_fallback_writes_the_same_file(tmp_path, monkeypatch):
    """Where direct I/O is refused (EINVAL, e.g. tmpfs) the same bytes go through the page cache."""
    image = np.arange(35, dtype=np.float32).reshape(5, 7)
    direct = _tiff.write_float32_tiff(tmp_path / "direct.tiff", image).read_bytes()
    real_open = os.open

    def no_direct(path, flags, mode=0o777):
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, mode)

    monkeypatch.setattr(os, "open", no_direct)
    cached = _tiff.write_float32_tiff(tmp_path / "cached.tiff", image).read_bytes()
    assert cached == direct and len(cached) == _tiff.DATA_OFFSET + image.nbytes


def test_no_space_is_raised(tmp_path, monkeypatch):
    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_direct_io, "_write_all", full)
    with pytest.raises(OSError) as info:
        _tiff.write_float32_tiff(tmp_path / "x.tiff", np.ones((4, 4), np.float32))
    assert info.value.errno == errno.ENOSPC


@pytest.mark.parametrize("n", [0, 1, 4095, 4096, 4097, 3 * 4096 + 5])
def test_write_bytes_any_length(tmp_path, n, monkeypatch):
    """Files of any length come out exact, direct or through the page cache."""
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert _direct_io.write_bytes(tmp_path / "a.bin", data).read_bytes() == data
    monkeypatch.setattr(os, "O_DIRECT", 0, raising=False)  # a system without direct I/O
    assert _direct_io.write_bytes(tmp_path / "b.bin", data).read_bytes() == data

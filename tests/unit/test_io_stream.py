"""``load_stack(stream=True)``: frames of uncompressed float stacks are views of
a read-only memory map (``.npy``, ``.tif``); everything else is read whole."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from afmdrift.io import ImageFileError, MissingPixelSizeError, load_stack


def _stack(n: int = 5, shape: tuple[int, int] = (24, 32)) -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.normal(0.0, 2.0, size=(n, *shape)).astype(np.float32)


def _mapped(a: np.ndarray) -> bool:
    while a is not None:
        if isinstance(a, np.memmap) or isinstance(getattr(a, "base", None), memoryview):
            return True
        if type(a.base).__name__ == "mmap":
            return True
        a = a.base  # type: ignore[assignment]
    return False


def _imagej_tif(path: Path, data: np.ndarray, **kw: object) -> Path:
    tifffile.imwrite(
        path,
        data,
        imagej=True,
        resolution=(1.0 / 1.5, 1.0 / 2.5),
        metadata={"axes": "TYX", "unit": "nm"},
        **kw,  # type: ignore[arg-type]
    )
    return path


def test_a_npy_stack_streams_as_views_of_a_memory_map(tmp_path: Path) -> None:
    data = _stack()
    np.save(tmp_path / "s.npy", data)
    frames = load_stack(tmp_path / "s.npy", pixel_size_nm=2.0, stream=True)
    whole = load_stack(tmp_path / "s.npy", pixel_size_nm=2.0)
    assert len(frames) == 5
    assert all(_mapped(f.heights_nm) for f in frames)
    assert not _mapped(whole[0].heights_nm)
    for f, w in zip(frames, whole, strict=True):
        np.testing.assert_array_equal(f.heights_nm, w.heights_nm)
        assert (f.frame, f.pixel_size_nm) == (w.frame, w.pixel_size_nm)


def test_a_tiff_stack_as_afmdrift_correct_writes_it_streams(tmp_path: Path) -> None:
    data = _stack()
    path = _imagej_tif(tmp_path / "s.tif", data)
    frames = load_stack(path, stream=True)
    whole = load_stack(path)
    assert all(_mapped(f.heights_nm) for f in frames)
    assert frames[0].pixel_size_nm == pytest.approx((1.5, 2.5))
    for f, w in zip(frames, whole, strict=True):
        np.testing.assert_array_equal(f.heights_nm, w.heights_nm)
        assert (f.frame, f.channel) == (w.frame, w.channel)
        assert f.pixel_size_nm == pytest.approx(w.pixel_size_nm)
    # a pixel size given overrides the file's, as when read whole
    given = load_stack(path, pixel_size_nm=4.0, stream=True)
    assert given[0].pixel_size_nm == (4.0, 4.0)


def test_a_compressed_or_integer_tiff_is_read_whole(tmp_path: Path) -> None:
    data = _stack()
    packed = _imagej_tif(tmp_path / "z.tif", data, compression="zlib")
    ints = _imagej_tif(tmp_path / "i.tif", (data * 100).astype(np.int16))
    for path in (packed, ints):
        frames = load_stack(path, stream=True)
        assert not _mapped(frames[0].heights_nm)
        np.testing.assert_allclose(frames[2].heights_nm, load_stack(path)[2].heights_nm)


def test_heights_in_another_unit_are_read_whole_and_scaled(tmp_path: Path) -> None:
    data = _stack()
    np.save(tmp_path / "s.npy", data)
    frames = load_stack(tmp_path / "s.npy", pixel_size_nm=1.0, height_unit="um", stream=True)
    assert not _mapped(frames[0].heights_nm)
    np.testing.assert_allclose(frames[1].heights_nm, data[1] * 1000.0, rtol=1e-6)


def test_a_truncated_tiff_stack_is_refused_by_name(tmp_path: Path) -> None:
    path = _imagej_tif(tmp_path / "t.tif", _stack(n=8, shape=(64, 64)))
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ImageFileError, match=r"t\.tif: ImageJ TIFF declares 8 images but holds 1"):
        load_stack(path, stream=True)


def test_a_streamed_npy_without_pixel_size_asks_for_it(tmp_path: Path) -> None:
    np.save(tmp_path / "s.npy", _stack())
    with pytest.raises(MissingPixelSizeError, match="--pixel-size-nm"):
        load_stack(tmp_path / "s.npy", stream=True)

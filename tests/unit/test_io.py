"""Image-file readers on files written here with known contents (no real data)."""

from __future__ import annotations

import struct
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import tifffile

from afmdrift.errors import InputError
from afmdrift.io import ImageFileError, length_unit_to_nm, load_image, load_stack, parse_spec
from afmdrift.records import ScanDirection


def _texture(rows: int = 24, cols: int = 32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(rows, cols))


# --------------------------------------------------------------------------- .npy


def test_npy_image_needs_pixel_size_and_keeps_heights(tmp_path: Path) -> None:
    img = _texture()
    p = tmp_path / "a.npy"
    np.save(p, img.astype(np.float32))
    with pytest.raises(ImageFileError, match=r"a\.npy.*pixel_size_nm"):
        load_image(p)
    im = load_image(p, pixel_size_nm=2.5)
    assert im.shape == (24, 32)
    assert im.heights_nm.dtype == np.float64
    assert im.pixel_size_nm == (2.5, 2.5)
    np.testing.assert_allclose(im.heights_nm, img.astype(np.float32))
    assert im.timestamp is None
    assert im.source == str(p)


def test_npy_height_unit_converts_to_nm(tmp_path: Path) -> None:
    p = tmp_path / "m.npy"
    np.save(p, np.full((4, 5), 2e-9))
    im = load_image(p, pixel_size_nm=(1.0, 2.0), height_unit="m")
    np.testing.assert_allclose(im.heights_nm, 2.0)
    assert im.pixel_size_nm == (1.0, 2.0)


def test_npy_stack_frames_and_frame_spec(tmp_path: Path) -> None:
    stack = np.stack([_texture(seed=i) for i in range(3)])
    p = tmp_path / "s.npy"
    np.save(p, stack)
    frames = load_stack(p, pixel_size_nm=1.0)
    assert [f.frame for f in frames] == [0, 1, 2]
    np.testing.assert_array_equal(load_image(f"{p}:2", pixel_size_nm=1.0).heights_nm, stack[2])
    with pytest.raises(ImageFileError, match=r"holds 3 frames"):
        load_image(p, pixel_size_nm=1.0)
    with pytest.raises(ImageFileError, match=r"frame 3 out of range.*0\.\.2"):
        load_image(f"{p}:3", pixel_size_nm=1.0)
    with pytest.raises(ImageFileError, match=r"frame -1 out of range"):
        load_image(f"{p}:-1", pixel_size_nm=1.0)


@pytest.mark.parametrize(
    ("array", "pattern"),
    [
        (np.zeros(5), r"must be \(rows, cols\)"),
        (np.zeros((2, 2, 2, 2)), r"must be \(rows, cols\)"),
        (np.array([[1.0, np.nan], [0.0, 0.0]]), "non-finite"),
        (np.array([["a", "b"]]), "numeric"),
    ],
)
def test_npy_bad_arrays_are_rejected(tmp_path: Path, array: np.ndarray, pattern: str) -> None:
    p = tmp_path / "bad.npy"
    np.save(p, array)
    with pytest.raises(ImageFileError, match=pattern):
        load_image(p, pixel_size_nm=1.0)


def test_truncated_npy_names_file(tmp_path: Path) -> None:
    p = tmp_path / "cut.npy"
    np.save(p, _texture())
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(ImageFileError, match=r"cut\.npy: not a readable \.npy"):
        load_image(p, pixel_size_nm=1.0)


# --------------------------------------------------------------------------- common errors


def test_missing_file_and_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(ImageFileError, match=r"nothere\.spm: no such file"):
        load_image(tmp_path / "nothere.spm")
    (tmp_path / "x.bmp").write_bytes(b"BM")
    with pytest.raises(ImageFileError, match=r"x\.bmp: unknown image file suffix '\.bmp'"):
        load_image(tmp_path / "x.bmp")
    with pytest.raises(ImageFileError, match="not a file"):
        load_image(tmp_path)


def test_errors_are_input_errors() -> None:
    """The CLI prints InputError (an AfmdriftError) without a traceback."""
    assert issubclass(ImageFileError, InputError)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), (1.0, 2.0, 3.0)])
def test_bad_pixel_size_is_rejected(tmp_path: Path, bad: object) -> None:
    p = tmp_path / "a.npy"
    np.save(p, _texture())
    with pytest.raises(ImageFileError, match="pixel_size_nm"):
        load_image(p, pixel_size_nm=bad)  # type: ignore[arg-type]


def test_parse_spec_splits_only_a_trailing_frame_number(tmp_path: Path) -> None:
    assert parse_spec("movie.asd:12") == (Path("movie.asd"), 12)
    assert parse_spec("movie.asd") == (Path("movie.asd"), None)
    assert parse_spec("C:/data/movie.asd") == (Path("C:/data/movie.asd"), None)


def test_length_units() -> None:
    assert length_unit_to_nm("m", where="t") == 1e9
    assert length_unit_to_nm("µm", where="t") == 1e3
    assert length_unit_to_nm("Å", where="t") == pytest.approx(0.1)
    with pytest.raises(ImageFileError, match="'V' is not a length unit"):
        length_unit_to_nm("V", where="t")


# --------------------------------------------------------------------------- .tif


def test_tiff_with_imagej_unit_gives_pixel_size(tmp_path: Path) -> None:
    img = _texture().astype(np.float32)
    p = tmp_path / "cal.tif"
    # 0.25 µm per pixel along x, 0.5 µm along y.
    tifffile.imwrite(p, img, imagej=True, resolution=(4.0, 2.0), metadata={"unit": "um"})
    im = load_image(p)
    assert im.pixel_size_nm == pytest.approx((250.0, 500.0))
    np.testing.assert_allclose(im.heights_nm, img)


def test_tiff_with_centimetre_resolution(tmp_path: Path) -> None:
    p = tmp_path / "cm.tif"
    tifffile.imwrite(p, _texture(), resolution=(1e6, 1e6), resolutionunit="CENTIMETER")
    assert load_image(p).pixel_size_nm == pytest.approx((10.0, 10.0))


def test_tiff_printing_resolution_is_not_a_calibration(tmp_path: Path) -> None:
    """Regression: a 72-dpi default must not become a 0.35 mm pixel size."""
    p = tmp_path / "dpi.tif"
    tifffile.imwrite(p, _texture(), resolution=(72, 72), resolutionunit="INCH")
    with pytest.raises(ImageFileError, match="pixel_size_nm"):
        load_image(p)
    assert load_image(p, pixel_size_nm=3.0).pixel_size_nm == (3.0, 3.0)


def test_tiff_stack_and_corrupt_tiff(tmp_path: Path) -> None:
    stack = np.stack([_texture(seed=i) for i in range(5)])
    p = tmp_path / "stack.tiff"
    tifffile.imwrite(p, stack)
    assert len(load_stack(p, pixel_size_nm=1.0)) == 5
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage")
    with pytest.raises(ImageFileError, match=r"bad\.tif: not a readable TIFF"):
        load_image(bad, pixel_size_nm=1.0)


# --------------------------------------------------------------------------- .nc


def _write_nc(
    path: Path, data: np.ndarray, *, units: str | None = "m", coords: bool = True
) -> None:
    from scipy.io import netcdf_file

    with netcdf_file(path, "w") as nc:
        nc.start_time = "2024-03-01T10:00:00"
        nc.line_time_s = 0.01
        nc.scan_direction = "down"
        dims = ("y", "x") if data.ndim == 2 else ("frame", "y", "x")
        if data.ndim == 3:
            nc.createDimension("frame", data.shape[0])
            t = nc.createVariable("time", "f8", ("frame",))
            t[:] = np.arange(data.shape[0]) * 2.0
            t.units = "s"
        nc.createDimension("y", data.shape[-2])
        nc.createDimension("x", data.shape[-1])
        if coords:
            x = nc.createVariable("x", "f8", ("x",))
            x[:] = np.arange(data.shape[-1]) * 2e-9
            x.units = "m"
            y = nc.createVariable("y", "f8", ("y",))
            y[:] = np.arange(data.shape[-2]) * 3e-9
            y.units = "m"
        h = nc.createVariable("height", "f8", dims)
        h[:] = data
        if units is not None:
            h.units = units


def test_netcdf_convention_stack(tmp_path: Path) -> None:
    data = np.stack([_texture(seed=i) for i in range(3)]) * 1e-9
    p = tmp_path / "movie.nc"
    _write_nc(p, data)
    frames = load_stack(p)
    assert len(frames) == 3
    f2 = frames[2]
    assert f2.pixel_size_nm == pytest.approx((2.0, 3.0))
    np.testing.assert_allclose(f2.heights_nm, data[2] * 1e9)
    assert f2.timestamp == datetime(2024, 3, 1, 10, 0, 4)
    assert f2.line_time_s == pytest.approx(0.01)
    assert f2.frame_time_s == pytest.approx(0.01 * 24)
    assert f2.scan_direction is ScanDirection.DOWN
    assert f2.channel == "height"
    np.testing.assert_allclose(load_image(f"{p}:1").heights_nm, data[1] * 1e9)


def test_netcdf_missing_units_and_coords(tmp_path: Path) -> None:
    p = tmp_path / "raw.nc"
    _write_nc(p, _texture(), units=None, coords=False)
    with pytest.raises(ImageFileError, match=r"variable 'height': heights have no unit"):
        load_image(p, pixel_size_nm=1.0)
    with pytest.raises(ImageFileError, match=r"no coordinate variable 'x'"):
        load_image(p, height_unit="nm")
    im = load_image(p, height_unit="um", pixel_size_nm=1.0)
    np.testing.assert_allclose(im.heights_nm, _texture() * 1e3)


def test_netcdf_wrong_variable_and_corrupt_file(tmp_path: Path) -> None:
    p = tmp_path / "a.nc"
    _write_nc(p, _texture() * 1e-9)
    with pytest.raises(ImageFileError, match=r"no variable 'Phase'.*height"):
        load_image(p, channel="Phase")
    p.write_bytes(p.read_bytes()[:60])
    with pytest.raises(ImageFileError, match=r"a\.nc: not a readable NetCDF-3"):
        load_image(p)


# --------------------------------------------------------------------------- .gwy


def _gwy_string(s: str) -> bytes:
    return s.encode() + b"\0"


def _gwy_object(name: str, components: list[tuple[str, str, bytes]]) -> bytes:
    body = b"".join(_gwy_string(n) + kind.encode() + value for n, kind, value in components)
    return _gwy_string(name) + struct.pack("<I", len(body)) + body


def _gwy_unit(unit: str) -> bytes:
    return _gwy_object("GwySIUnit", [("unitstr", "s", _gwy_string(unit))])


def _write_gwy(
    path: Path, data: np.ndarray, *, xy: str, z: str, xreal: float, yreal: float
) -> None:
    rows, cols = data.shape
    field = _gwy_object(
        "GwyDataField",
        [
            ("xres", "i", struct.pack("<i", cols)),
            ("yres", "i", struct.pack("<i", rows)),
            ("xreal", "d", struct.pack("<d", xreal)),
            ("yreal", "d", struct.pack("<d", yreal)),
            ("si_unit_xy", "o", _gwy_unit(xy)),
            ("si_unit_z", "o", _gwy_unit(z)),
            ("data", "D", struct.pack("<I", data.size) + data.astype("<f8").tobytes()),
        ],
    )
    container = _gwy_object(
        "GwyContainer",
        [("/0/data/title", "s", _gwy_string("Topography")), ("/0/data", "o", field)],
    )
    path.write_bytes(b"GWYP" + container)


def test_gwy_non_square_field_in_metres(tmp_path: Path) -> None:
    """Regression: data are row-major (yres rows of xres); a (xres, yres) reshape
    would scramble a non-square field; heights use si_unit_z, not si_unit_xy."""
    data = _texture(rows=6, cols=10) * 1e-9
    p = tmp_path / "f.gwy"
    _write_gwy(p, data, xy="m", z="m", xreal=10 * 4e-9, yreal=6 * 5e-9)
    im = load_image(p)
    assert im.shape == (6, 10)
    assert im.channel == "Topography"
    assert im.pixel_size_nm == pytest.approx((4.0, 5.0))
    np.testing.assert_allclose(im.heights_nm, data * 1e9)


def test_gwy_unitless_field_needs_units(tmp_path: Path) -> None:
    p = tmp_path / "u.gwy"
    _write_gwy(p, _texture(), xy="", z="", xreal=32.0, yreal=24.0)
    with pytest.raises(ImageFileError, match="heights have no unit"):
        load_image(p)
    with pytest.raises(ImageFileError, match="no lateral unit"):
        load_image(p, height_unit="nm")
    im = load_image(p, height_unit="pm", pixel_size_nm=1.5)
    np.testing.assert_allclose(im.heights_nm, _texture() * 1e-3)
    with pytest.raises(ImageFileError, match=r"channel 'Phase' not in this Gwyddion file"):
        load_image(p, channel="Phase", height_unit="nm", pixel_size_nm=1.0)


def test_gwy_truncated_and_not_gwy(tmp_path: Path) -> None:
    p = tmp_path / "t.gwy"
    _write_gwy(p, _texture(), xy="m", z="m", xreal=1e-6, yreal=1e-6)
    p.write_bytes(p.read_bytes()[:-100])
    with pytest.raises(ImageFileError, match=r"t\.gwy: Gwyddion file is truncated"):
        load_image(p)
    p.write_bytes(b"not a gwy file")
    with pytest.raises(ImageFileError, match="no 'GWYP' magic"):
        load_image(p)


# --------------------------------------------------------------------------- NanoScope


def test_nanoscope_without_header_is_rejected(tmp_path: Path) -> None:
    for name in ("x.spm", "x.001"):
        p = tmp_path / name
        p.write_bytes(b"\0" * 100)
        with pytest.raises(ImageFileError, match="not a NanoScope file"):
            load_image(p)


def test_nanoscope_header_without_end_is_truncated(tmp_path: Path) -> None:
    p = tmp_path / "h.000"
    p.write_bytes(
        b"\\*File list\r\n\\Version: 0x05310001\r\n\\Date: 12:34:38 PM Tue Jul 30 2019\r\n"
    )
    with pytest.raises(ImageFileError, match="header is truncated"):
        load_image(p)

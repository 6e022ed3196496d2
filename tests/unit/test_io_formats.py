"""Readers and writers added for folder instruments and ``afmdrift measure``:
Nanonis ``.sxm`` and timed ImageJ ``.tif`` (files written here, known contents)."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from _afm_writers import write_nc4 as _write_nc4

from afmdrift.io import ImageFileError, load_image, write_sxm, write_tif
from afmdrift.records import ScanDirection

START = datetime(2025, 3, 4, 5, 6, 7)


def _texture(rows: int = 24, cols: int = 32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=3.0, size=(rows, cols))


@pytest.mark.parametrize("direction", [ScanDirection.UP, ScanDirection.DOWN])
def test_sxm_round_trip_keeps_heights_calibration_and_timing(
    tmp_path: Path, direction: ScanDirection
) -> None:
    img = _texture()
    p = write_sxm(
        tmp_path / "scan.sxm",
        img,
        pixel_size_nm=(2.0, 3.0),
        start=START,
        line_time_s=0.25,
        direction=direction,
    )
    im = load_image(p)
    np.testing.assert_allclose(im.heights_nm, img, rtol=1e-6, atol=1e-5)  # float32 in m
    assert im.pixel_size_nm == pytest.approx((2.0, 3.0))
    assert im.channel == "Z"
    assert im.timestamp == START
    assert im.line_time_s == pytest.approx(0.25)
    assert im.frame_time_s == pytest.approx(0.25 * 24)
    assert im.scan_direction is direction


def test_sxm_down_scan_is_stored_top_line_first(tmp_path: Path) -> None:
    """Nanonis stores lines in scan order: a down scan's first stored line is the top one."""
    img = np.arange(12, dtype=np.float64).reshape(3, 4)
    up = write_sxm(tmp_path / "u.sxm", img, pixel_size_nm=(1, 1), start=START, line_time_s=1.0)
    down = write_sxm(
        tmp_path / "d.sxm",
        img,
        pixel_size_nm=(1, 1),
        start=START,
        line_time_s=1.0,
        direction=ScanDirection.DOWN,
    )
    first_up = np.frombuffer(up.read_bytes()[-48:-32], ">f4") * 1e9
    first_down = np.frombuffer(down.read_bytes()[-48:-32], ">f4") * 1e9
    np.testing.assert_allclose(first_up, img[0], atol=1e-5)
    np.testing.assert_allclose(first_down, img[2], atol=1e-5)


def _sxm_bytes(tmp_path: Path) -> bytes:
    return write_sxm(
        tmp_path / "ok.sxm", _texture(8, 8), pixel_size_nm=(1, 1), start=START, line_time_s=0.1
    ).read_bytes()


@pytest.mark.parametrize("keep", [0.2, 0.5, 0.9, 0.999])
def test_sxm_truncated_anywhere_is_refused(tmp_path: Path, keep: float) -> None:
    data = _sxm_bytes(tmp_path)
    p = tmp_path / "cut.sxm"
    p.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ImageFileError, match=r"cut\.sxm.*truncated"):
        load_image(p)


@pytest.mark.parametrize(
    ("old", "new", "pattern"),
    [
        (b":SCAN_PIXELS:\n       8       8", b":SCAN_PIXELS:\n       x       8", "not numeric"),
        (b"FLOAT            MSBFIRST", b"COMPLEX          MSBFIRST", "SCANIT_TYPE"),
        (b"\tZ\tm\t", b"\tZ\tV\t", "not a length unit"),
        (b"\tChannel\tName", b"\tKanal\tName", "DATA_INFO"),
        (b":REC_DATE:\n04.03.2025", b":REC_DATE:\n34.13.2025", "REC_DATE"),
        (b":SCAN_RANGE:", b":SCAN_RANGX:", "SCAN_RANGE"),
    ],
)
def test_sxm_garbled_header_names_the_problem(
    tmp_path: Path, old: bytes, new: bytes, pattern: str
) -> None:
    data = _sxm_bytes(tmp_path)
    assert old in data
    p = tmp_path / "bad.sxm"
    p.write_bytes(data.replace(old, new))
    with pytest.raises(ImageFileError, match=rf"bad\.sxm.*{pattern}"):
        load_image(p)


def test_sxm_unknown_channel_and_not_sxm(tmp_path: Path) -> None:
    p = tmp_path / "ok.sxm"
    p.write_bytes(_sxm_bytes(tmp_path))
    with pytest.raises(ImageFileError, match=r"no channel 'Current'.*has: Z"):
        load_image(p, channel="Current")
    junk = tmp_path / "junk.sxm"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(ImageFileError, match=r"junk\.sxm.*not a Nanonis"):
        load_image(junk)


def test_timed_tif_round_trip(tmp_path: Path) -> None:
    img = _texture()
    p = write_tif(
        tmp_path / "f.tif",
        img,
        pixel_size_nm=(2.0, 2.5),
        start=datetime(2025, 1, 2, 3, 4, 5, 250000),
        line_time_s=0.125,
        direction=ScanDirection.DOWN,
    )
    im = load_image(p)
    np.testing.assert_allclose(im.heights_nm, img.astype(np.float32))
    assert im.pixel_size_nm == pytest.approx((2.0, 2.5), rel=1e-6)
    assert im.timestamp == datetime(2025, 1, 2, 3, 4, 5, 250000)
    assert im.line_time_s == 0.125
    assert im.frame_time_s == pytest.approx(3.0)
    assert im.scan_direction is ScanDirection.DOWN


def test_tif_without_timing_has_none(tmp_path: Path) -> None:
    im = load_image(write_tif(tmp_path / "f.tif", _texture(), pixel_size_nm=(1.0, 1.0)))
    assert im.timestamp is None
    assert im.line_time_s is None


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.95])
def test_truncated_tif_is_refused(tmp_path: Path, keep: float) -> None:
    data = write_tif(tmp_path / "ok.tif", _texture(64, 64), pixel_size_nm=(1, 1)).read_bytes()
    p = tmp_path / "cut.tif"
    p.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ImageFileError, match=r"cut\.tif"):
        load_image(p)


# --------------------------------------------------------------------------- NetCDF-4


def test_netcdf4_round_trip(tmp_path: Path) -> None:
    img = _texture()
    im = load_image(_write_nc4(tmp_path / "afspm.nc", img * 1e-9))
    np.testing.assert_allclose(im.heights_nm, img, rtol=1e-12, atol=1e-12)
    assert im.pixel_size_nm == pytest.approx((2.0, 2.0))
    assert im.timestamp == START
    assert im.line_time_s == 0.5
    assert im.scan_direction is ScanDirection.DOWN


def test_netcdf4_missing_variable_and_truncated(tmp_path: Path) -> None:
    p = _write_nc4(tmp_path / "a.nc", _texture() * 1e-9)
    with pytest.raises(ImageFileError, match=r"no variable 'Phase'.*Height"):
        load_image(p, channel="Phase")
    cut = tmp_path / "cut.nc"
    cut.write_bytes(p.read_bytes()[:1000])
    with pytest.raises(ImageFileError, match=r"cut\.nc"):
        load_image(cut)


# --------------------------------------------------------------------------- calibration bounds


def test_implausible_pixel_size_is_refused_with_the_value(tmp_path: Path) -> None:
    p = write_tif(tmp_path / "f.tif", _texture(), pixel_size_nm=(1.0, 1.0))
    with pytest.raises(ImageFileError, match=r"implausible pixel size along x: 1\.07e\+07 nm"):
        load_image(p, pixel_size_nm=1.07e7)
    with pytest.raises(ImageFileError, match=r"implausible pixel size along y: 0\.0001 nm"):
        load_image(p, pixel_size_nm=(1.0, 1e-4))


def test_implausible_height_range_is_refused(tmp_path: Path) -> None:
    img = _texture(8, 8)
    img[0, 0] = 2e5
    p = write_sxm(tmp_path / "z.sxm", img, pixel_size_nm=(1, 1), start=START, line_time_s=0.1)
    with pytest.raises(ImageFileError, match=r"implausible height range 2e\+05 nm"):
        load_image(p)

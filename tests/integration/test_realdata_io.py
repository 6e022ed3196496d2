"""Readers on the real AFM files in ``shared/data/real`` (see its README)."""

from __future__ import annotations

import re
from collections.abc import Callable
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from afmdrift.io import ImageFileError, load_image, load_stack, parse_nanoscope_header
from afmdrift.records import ScanDirection

pytestmark = pytest.mark.realdata

RealFile = Callable[[str], Path]


def _raw_nanoscope_nm(path: Path) -> np.ndarray:
    """Independent decoding: int16 words at ``Data offset`` × Z scale (V/LSB) × Zscan (nm/V)."""
    header = parse_nanoscope_header(path)
    offset = int(header.number("Data offset") or 0)
    rows, cols = int(header.number("Number of lines") or 0), int(header.number("Samps/line") or 0)
    z_scale_text = header.first("@2:Z scale") or ""
    found = re.search(r"\(([-\d.eE+]+) V/LSB\)", z_scale_text)
    assert found is not None, z_scale_text
    volts_per_lsb = float(found.group(1))
    sens = header.number("@Sens. Zscan")
    raw = np.frombuffer(path.read_bytes()[offset : offset + 2 * rows * cols], dtype="<i2")
    return raw.reshape(rows, cols).astype(np.float64) * volts_per_lsb * float(sens or 0)


@pytest.mark.parametrize(
    ("name", "date"),
    [
        ("nanoscope3a_15um.002", datetime(2019, 7, 30, 12, 34, 38)),
        ("nanoscope3a_15um.004", datetime(2019, 7, 30, 12, 45, 17)),
    ],
)
def test_nanoscope_files(real_file: RealFile, name: str, date: datetime) -> None:
    path = real_file(name)
    im = load_image(path)
    assert im.shape == (256, 256)
    assert im.pixel_size_nm == pytest.approx((15000 / 256, 15000 / 256))
    assert im.line_time_s == pytest.approx(1 / 1.50498)
    assert im.frame_time_s == pytest.approx(256 / 1.50498)
    # \Date marks the end of the capture; timestamp is the start of the scan.
    assert im.timestamp is not None
    assert im.frame_time_s is not None
    end = im.timestamp + timedelta(seconds=im.frame_time_s)
    assert abs(end - date) < timedelta(milliseconds=1)
    assert im.scan_direction is ScanDirection.UP
    assert im.channel == "Height"
    # Heights in nm and rows in stored order: equal to our own decoding of the raw data.
    # (rtol: pySPM uses the hard Z scale / 2**16 rather than the rounded V/LSB figure.)
    np.testing.assert_allclose(im.heights_nm, _raw_nanoscope_nm(path), rtol=1e-4)
    assert 50 < im.heights_nm.std() < 500  # tens to hundreds of nm over 15 µm


def test_nanoscope_wrong_channel_and_truncation(real_file: RealFile, tmp_path: Path) -> None:
    path = real_file("nanoscope3a_15um.002")
    with pytest.raises(ImageFileError, match=r"no channel 'Phase' \(has: Height\)"):
        load_image(path, channel="Phase")
    cut = tmp_path / "cut.002"
    cut.write_bytes(path.read_bytes()[:100_000])
    with pytest.raises(ImageFileError, match=r"cut\.002: cannot read channel 'Height'"):
        load_image(cut)


def test_hsafm_movie(real_file: RealFile) -> None:
    path = real_file("hsafm_sample_0.asd")
    frames = load_stack(path)
    assert len(frames) == 32
    assert all(f.shape == (200, 200) and f.pixel_size_nm == (0.5, 0.5) for f in frames)
    assert frames[0].channel == "TP"
    assert frames[0].frame_time_s == pytest.approx(1.0)
    assert frames[0].line_time_s is None
    assert frames[0].timestamp == datetime(2017, 11, 21, 13, 12, 39)
    assert frames[31].timestamp == datetime(2017, 11, 21, 13, 13, 10)
    # Heights in nm: sub-nm roughness on the early frames; frame 28 is blank.
    assert 0.1 < float(frames[0].heights_nm.std()) < 1.0
    assert float(frames[28].heights_nm.std()) < 1e-6
    one = load_image(f"{path}:5")
    np.testing.assert_array_equal(one.heights_nm, frames[5].heights_nm)
    assert one.source.endswith("hsafm_sample_0.asd:5")


def test_hsafm_errors(real_file: RealFile, tmp_path: Path) -> None:
    path = real_file("hsafm_sample_0.asd")
    with pytest.raises(ImageFileError, match=r"frame 32 out of range"):
        load_image(f"{path}:32")
    with pytest.raises(ImageFileError, match=r"holds 32 frames"):
        load_image(path)
    with pytest.raises(ImageFileError, match=r"'PH' not found"):
        load_image(f"{path}:0", channel="PH")
    cut = tmp_path / "cut.asd"
    cut.write_bytes(path.read_bytes()[:1_000_000])
    with pytest.raises(ImageFileError, match=r"cut\.asd: truncated or corrupt"):
        load_stack(cut)


def test_gwyddion_file_is_unitless(real_file: RealFile) -> None:
    """The sample .gwy has one field titled 'Test', 128×128, with empty SI units."""
    path = real_file("gwyddion_test.gwy")
    with pytest.raises(ImageFileError, match="heights have no unit"):
        load_image(path)
    im = load_image(path, height_unit="nm", pixel_size_nm=1.0)
    assert im.shape == (128, 128)
    assert im.channel == "Test"
    assert np.all(np.isfinite(im.heights_nm))
    with pytest.raises(ImageFileError, match=r"\(has: Test\)"):
        load_image(path, channel="Phase", height_unit="nm", pixel_size_nm=1.0)


def test_afmreader_logging_is_silenced(
    real_file: RealFile, capfd: pytest.CaptureFixture[str]
) -> None:
    """Regression: AFMReader re-enables its loguru logging on import; nothing may
    reach the terminal when afmdrift reads a file."""
    load_image(real_file("nanoscope3a_15um.002"))
    load_image(f"{real_file('hsafm_sample_0.asd')}:0")
    out, err = capfd.readouterr()
    assert out == ""
    assert err == ""


@pytest.mark.parametrize("suffix", [".spm", ".SPM", ".000"])
def test_nanoscope_any_suffix(real_file: RealFile, tmp_path: Path, suffix: str) -> None:
    """A NanoScope file reads the same under .spm and any numbered suffix."""
    src = real_file("nanoscope3a_15um.002")
    copy = tmp_path / f"scan{suffix}"
    copy.write_bytes(src.read_bytes())
    np.testing.assert_array_equal(load_image(copy).heights_nm, load_image(src).heights_nm)

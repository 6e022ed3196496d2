"""Asylum ``.ibw``, JPK ``.jpk``/``.h5-jpk`` and WSxM ``.stp`` (issues 13 and 15).

No recorded files of these formats are available, so each test writes one from
the format's documented layout (``_afm_writers``) with known heights,
calibration and timing, reads it back through ``load_image``/``load_stack``,
then breaks it: truncated or garbled files must give one ``ImageFileError``
naming the file and the problem.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from _afm_writers import igor_wave5, write_h5jpk, write_ibw, write_jpk, wsxm_stp

from afmdrift.drivers._folder import _is_image_name
from afmdrift.io import SUFFIXES, ImageFileError, load_image, load_stack
from afmdrift.records import ScanDirection

ROWS, COLS = 12, 16


def _heights_nm(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=3.0, size=(ROWS, COLS))


ASYLUM_NOTE = {
    "ScanSize": "3.2e-08",
    "FastScanSize": "3.2e-08",
    "SlowScanSize": "4.8e-08",
    "ScanRate": "2",
    "ScanPoints": str(COLS),
    "ScanLines": str(ROWS),
    "ScanDown": "1",
    "Date": "2024-05-06",
    "Time": "1:02:30 PM",
}


def _ibw(tmp_path: Path, name: str = "scan.ibw", **kwargs: object) -> Path:
    h = _heights_nm()
    layers = {"HeightTrace": h * 1e-9, "HeightRetrace": h * 2e-9, "PhaseTrace": h}
    return write_ibw(tmp_path / name, layers, note=dict(ASYLUM_NOTE), **kwargs)


# --------------------------------------------------------------------------- .ibw


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ibw_reads_heights_pixel_size_and_timing(tmp_path: Path, byte_order: str) -> None:
    im = load_image(_ibw(tmp_path, byte_order=byte_order))
    np.testing.assert_allclose(im.heights_nm, _heights_nm(), rtol=1e-6, atol=1e-5)  # float32
    assert im.channel == "HeightTrace"
    assert im.pixel_size_nm == pytest.approx((2.0, 4.0))  # 32 nm / 16, 48 nm / 12
    assert im.line_time_s == pytest.approx(0.5)
    assert im.frame_time_s == pytest.approx(6.0)
    # The note's date marks the end of the frame; the scan started one frame earlier.
    assert im.timestamp == datetime(2024, 5, 6, 13, 2, 24)
    assert im.scan_direction is ScanDirection.DOWN


def test_ibw_channel_selection_uses_asylum_names(tmp_path: Path) -> None:
    p = _ibw(tmp_path)
    retrace = load_image(p, channel="HeightRetrace")
    np.testing.assert_allclose(retrace.heights_nm, 2 * _heights_nm(), rtol=1e-6, atol=1e-5)
    assert load_image(p, channel="height").channel == "HeightTrace"
    with pytest.raises(ImageFileError, match=r"scan\.ibw: no channel 'ZSensor'.*HeightTrace"):
        load_image(p, channel="ZSensor")
    with pytest.raises(ImageFileError, match=r"scan\.ibw: channel 'PhaseTrace' has no length"):
        load_image(p, channel="Phase")


def test_ibw_data_unit_is_used(tmp_path: Path) -> None:
    p = write_ibw(
        tmp_path / "um.ibw",
        {"HeightTrace": _heights_nm() * 1e-3},
        note=ASYLUM_NOTE,
        data_units="um",
    )
    np.testing.assert_allclose(load_image(p).heights_nm, _heights_nm(), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("keep", [0.001, 0.05, 0.3, 0.7, 0.99])
def test_ibw_truncated_anywhere_is_refused(tmp_path: Path, keep: float) -> None:
    data = _ibw(tmp_path).read_bytes()
    p = tmp_path / "cut.ibw"
    p.write_bytes(data[: max(1, int(len(data) * keep))])
    with pytest.raises(ImageFileError, match=r"cut\.ibw.*(truncated|not an Igor)"):
        load_image(p)


@pytest.mark.parametrize(
    ("old", "new", "pattern"),
    [
        (b"FastScanSize: 3.2e-08", b"FastScanSize: 3.2e+08", "implausible pixel size along x"),
        (b"SlowScanSize: 4.8e-08", b"SlowScanSize: abcdefg", "SlowScanSize 'abcdefg' is not"),
        (b"ScanRate: 2", b"ScanRate: -2", "ScanRate must be positive"),
        (b"Date: 2024-05-06", b"Date: 2024-13-06", "Date/Time"),
    ],
)
def test_ibw_garbled_note_names_the_problem(
    tmp_path: Path, old: bytes, new: bytes, pattern: str
) -> None:
    data = _ibw(tmp_path).read_bytes()
    assert old in data
    p = tmp_path / "bad.ibw"
    p.write_bytes(data.replace(old, new))
    with pytest.raises(ImageFileError, match=rf"bad\.ibw.*{pattern}"):
        load_image(p)


def test_ibw_garbled_headers_are_refused(tmp_path: Path) -> None:
    good = igor_wave5({"HeightTrace": _heights_nm() * 1e-9}, note=ASYLUM_NOTE)
    cases = {
        "version": b"\x07\x00" + good[2:],  # version 7 does not exist
        "npnts": good[:76] + b"\xff\xff\xff\x7f" + good[80:],  # npnts = 2**31 - 1
        "type": good[:80] + b"\x00\x00" + good[82:],  # a text wave
        "notesize": good[:12] + b"\xff\xff\xff\x0f" + good[16:],  # note of 256 MiB
    }
    for name, data in cases.items():
        p = tmp_path / f"{name}.ibw"
        p.write_bytes(data)
        with pytest.raises(ImageFileError, match=rf"{name}\.ibw: "):
            load_image(p)


# --------------------------------------------------------------------------- .jpk


def _jpk(
    tmp_path: Path, name: str = "scan.jpk", start: str = "2024-05-06 13:02:03.25 CEST"
) -> Path:
    h = _heights_nm() * 1e-9
    return write_jpk(
        tmp_path / name,
        {("height", False): h, ("height", True): 2 * h, ("measuredHeight", False): 3 * h},
        size_m=(3.2e-8, 4.8e-8),
        line_rate_hz=4.0,
        start=start,
    )


def test_jpk_reads_heights_pixel_size_and_timing(tmp_path: Path) -> None:
    im = load_image(_jpk(tmp_path))
    np.testing.assert_allclose(im.heights_nm, _heights_nm(), atol=1e-3)  # raw steps of 1 pm
    assert im.channel == "height_trace"
    assert im.pixel_size_nm == pytest.approx((2.0, 4.0))
    assert im.line_time_s == pytest.approx(0.25)
    assert im.frame_time_s == pytest.approx(3.0)
    assert im.timestamp == datetime(2024, 5, 6, 13, 2, 3, 250000)
    assert im.scan_direction is None


def test_jpk_channel_selection_and_unknown_date(tmp_path: Path) -> None:
    p = _jpk(tmp_path, start="Mon May 06 13:02:03 CEST 2024")
    assert load_image(p).timestamp is None  # a date form we do not know: no timestamp
    retrace = load_image(p, channel="height_retrace")
    np.testing.assert_allclose(retrace.heights_nm, 2 * _heights_nm(), atol=1e-3)
    sensor = load_image(p, channel="measuredHeight")
    assert sensor.channel == "measuredheight_trace"
    np.testing.assert_allclose(sensor.heights_nm, 3 * _heights_nm(), atol=1e-3)
    with pytest.raises(ImageFileError, match=r"scan\.jpk: no channel 'Phase'.*height_trace"):
        load_image(p, channel="Phase")


@pytest.mark.parametrize("keep", [0.05, 0.3, 0.6, 0.95])
def test_jpk_truncated_is_refused(tmp_path: Path, keep: float) -> None:
    data = _jpk(tmp_path).read_bytes()
    p = tmp_path / "cut.jpk"
    p.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ImageFileError, match=r"cut\.jpk.*(truncated|not a readable)"):
        load_image(p)


def test_jpk_garbled_tags_name_the_problem(tmp_path: Path) -> None:
    data = _jpk(tmp_path).read_bytes()
    p = tmp_path / "bad.jpk"
    p.write_bytes(data.replace(b"LinearScaling", b"CubicScaling!"))
    with pytest.raises(ImageFileError, match=r"bad\.jpk.*scaling 'CubicScaling!'"):
        load_image(p)
    plain = tmp_path / "plain.jpk"
    import tifffile

    tifffile.imwrite(plain, np.zeros((4, 4), np.float32))
    with pytest.raises(ImageFileError, match=r"plain\.jpk: not a JPK image scan"):
        load_image(plain)


# --------------------------------------------------------------------------- .h5-jpk


def test_h5jpk_movie_reads_every_frame(tmp_path: Path) -> None:
    frames = np.stack([_heights_nm(k)[:, :ROWS] for k in range(3)])
    p = write_h5jpk(
        tmp_path / "movie.h5-jpk", frames * 1e-9, size_m=(3.6e-8, 2.4e-8), line_rate_hz=8
    )
    stack = load_stack(p)
    assert [im.frame for im in stack] == [0, 1, 2]
    for im, want in zip(stack, frames, strict=True):
        np.testing.assert_allclose(im.heights_nm, want, atol=1e-9)
        assert im.pixel_size_nm == pytest.approx((3.0, 2.0))
        assert im.line_time_s == pytest.approx(0.125)
        assert im.frame_time_s == pytest.approx(1.5)
    assert load_image(f"{p}:2").frame == 2


def test_h5jpk_refusals_name_the_problem(tmp_path: Path) -> None:
    frames = np.stack([_heights_nm(k)[:, :ROWS] for k in range(2)]) * 1e-9
    p = write_h5jpk(tmp_path / "m.h5-jpk", frames, size_m=(3e-8, 3e-8), line_rate_hz=8)
    with pytest.raises(ImageFileError, match=r"m\.h5-jpk: channel 'Phase' is not a height"):
        load_stack(p, channel="Phase")
    with pytest.raises(ImageFileError, match=r"m\.h5-jpk.*'measuredheight_trace' not found"):
        load_stack(p, channel="measuredHeight")
    odd = write_h5jpk(
        tmp_path / "odd.h5-jpk", frames, size_m=(3e-8, 3e-8), line_rate_hz=8, square=False
    )
    with pytest.raises(ImageFileError, match=r"odd\.h5-jpk: grid of 12 × 13.*square"):
        load_stack(odd)
    cut = tmp_path / "cut.h5-jpk"
    cut.write_bytes(p.read_bytes()[:3000])
    with pytest.raises(ImageFileError, match=r"cut\.h5-jpk"):
        load_stack(cut)


# --------------------------------------------------------------------------- .stp


def _stp(tmp_path: Path, name: str = "scan.stp", **kwargs: object) -> Path:
    p = tmp_path / name
    p.write_bytes(wsxm_stp(_heights_nm(), size=("32 nm", "0.048 µm"), **kwargs))  # type: ignore[arg-type]
    return p


def test_stp_reads_heights_pixel_size_and_timing(tmp_path: Path) -> None:
    im = load_image(_stp(tmp_path))
    np.testing.assert_allclose(im.heights_nm, _heights_nm(), rtol=0, atol=0)  # float64 in nm
    assert im.channel == "Topography"
    assert im.pixel_size_nm == pytest.approx((2.0, 4.0))
    assert im.line_time_s == pytest.approx(0.5)
    assert im.frame_time_s == pytest.approx(6.0)
    assert im.timestamp is None
    assert im.scan_direction is None


def test_stp_z_unit_and_channel(tmp_path: Path) -> None:
    p = tmp_path / "a.stp"
    p.write_bytes(wsxm_stp(_heights_nm() * 10, size=("320 Å", "480 Å"), z_unit="Å"))
    im = load_image(p)
    np.testing.assert_allclose(im.heights_nm, _heights_nm(), atol=1e-12)
    assert im.pixel_size_nm == pytest.approx((2.0, 4.0))
    with pytest.raises(ImageFileError, match=r"a\.stp: no channel 'Phase'.*Topography"):
        load_image(p, channel="Phase")


@pytest.mark.parametrize("keep", [0.01, 0.2, 0.5, 0.9, 0.999])
def test_stp_truncated_anywhere_is_refused(tmp_path: Path, keep: float) -> None:
    data = _stp(tmp_path).read_bytes()
    p = tmp_path / "cut.stp"
    p.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ImageFileError, match=r"cut\.stp.*(truncated|not a WSxM|Header end)"):
        load_image(p)


@pytest.mark.parametrize(
    ("old", "new", "pattern"),
    [
        (b"Number of rows: 12", b"Number of rows: x2", "'number of rows' is 'x2'"),
        (b"X Amplitude: 32 nm", b"X Amplitude: 32 V ", "not a length unit"),
        (b"X Amplitude: 32 nm", b"X Amplitude: 3e9 m", "implausible pixel size along x"),
        (b"Image Data Type: double", b"Image Data Type: short ", "Image Data Type: short"),
        (b"[Header end]", b"[Header e?d]", r"\[Header end\]"),
        (b"Image header size: 0", b"Image header size: 9", "truncated"),
        (b"X-Frequency: 2 Hz", b"X-Frequency: fast", "X Frequency"),
    ],
)
def test_stp_garbled_header_names_the_problem(
    tmp_path: Path, old: bytes, new: bytes, pattern: str
) -> None:
    data = _stp(tmp_path).read_bytes()
    assert old in data
    p = tmp_path / "bad.stp"
    p.write_bytes(data.replace(old, new, 1))
    with pytest.raises(ImageFileError, match=rf"bad\.stp.*{pattern}"):
        load_image(p)


# --------------------------------------------------------------------------- registration


@pytest.mark.parametrize("suffix", [".ibw", ".jpk", ".h5-jpk", ".stp"])
def test_new_suffixes_are_known_to_load_and_the_folder_instrument(suffix: str) -> None:
    assert suffix in SUFFIXES
    assert _is_image_name(f"frame_0001{suffix}")
    assert _is_image_name(f"FRAME_0001{suffix.upper()}")

"""``afmdrift import`` of the real AFM files, re-read with ``read_session``."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.io import load_image
from afmdrift.session import read_session

pytestmark = pytest.mark.realdata

RealFile = Callable[[str], Path]


def test_import_nanoscope_series_sorted_by_header_time(
    real_file: RealFile, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b = real_file("nanoscope3a_15um.002"), real_file("nanoscope3a_15um.004")
    out = tmp_path / "ns"
    # Given in reverse order: the header dates put .002 first.
    assert main(["import", str(b), str(a), "--out", str(out)]) == 0
    assert "2 frame(s) of 256x256 px" in capsys.readouterr().out
    s = read_session(out)
    assert s.meta.pixel_size_nm == pytest.approx((58.59375, 58.59375))
    assert s.meta.line_time_s == pytest.approx(1 / 1.50498)
    frame_s = 256 / 1.50498
    # Dates 12:34:38 and 12:45:17 (capture ends) -> starts 639 s apart.
    np.testing.assert_allclose(s.frame_times, [[0, frame_s], [639, 639 + frame_s]])
    assert [d.value for d in s.directions] == ["up", "up"]
    assert s.meta.start_time.startswith("2019-07-30T12:31:47")
    np.testing.assert_array_equal(np.asarray(s.frames[0]), load_image(a).heights_nm)
    np.testing.assert_array_equal(np.asarray(s.frames[1]), load_image(b).heights_nm)
    assert s.meta.extra["frame_sources"] == [str(a), str(b)]


def test_import_hsafm_movie(real_file: RealFile, tmp_path: Path) -> None:
    path = real_file("hsafm_sample_0.asd")
    out = tmp_path / "asd"
    assert main(["import", str(path), "--out", str(out)]) == 0
    s = read_session(out)
    assert np.asarray(s.frames).shape == (32, 200, 200)
    np.testing.assert_allclose(s.frame_times[:, 0], np.arange(32.0))
    np.testing.assert_allclose(s.frame_times[:, 1], np.arange(32.0) + 1.0)
    assert s.meta.line_time_s == pytest.approx(1.0 / 200)
    assert "frame time / rows" in s.meta.source
    assert s.meta.start_time == "2017-11-21T13:12:39"
    assert s.meta.pixel_size_nm == (0.5, 0.5)


def test_import_gwyddion_needs_units_and_timing(
    real_file: RealFile, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = real_file("gwyddion_test.gwy")
    out = tmp_path / "gwy"
    assert main(["import", str(path), "--out", str(out)]) == 2
    assert "heights have no unit" in capsys.readouterr().err
    args = ["import", str(path), "--out", str(out), "--height-unit", "nm"]
    assert main([*args, "--pixel-size-nm", "1"]) == 2
    assert "no frame timing" in capsys.readouterr().err
    assert main([*args, "--pixel-size-nm", "1", "--frame-time-s", "64", "--force"]) == 0
    s = read_session(out)
    assert np.asarray(s.frames).shape == (1, 128, 128)
    assert s.meta.line_time_s == pytest.approx(0.5)


def test_import_mixed_shapes_names_the_file(
    real_file: RealFile, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ns = real_file("nanoscope3a_15um.002")
    asd = real_file("hsafm_sample_0.asd")
    assert main(["import", str(ns), str(asd), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "hsafm_sample_0.asd:0: image is 200x200 px" in err
    assert "nanoscope3a_15um.002 is 256x256" in err

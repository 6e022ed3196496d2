"""The default channel ``Height`` finds each format's height channel
(issue 29: afspm's NetCDF-4 files name it ``HeightRetrace``, and ``afmdrift
measure`` answered "no variable 'Height'"); the channel taken is reported."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _afm_writers import write_ibw, write_nc4

from afmdrift.cli import main
from afmdrift.io import ImageFileError, load_image, pick_channel
from afmdrift.testing import fourier_shift, rough_texture


def _heights(rows: int = 24, cols: int = 32) -> np.ndarray:
    return np.random.default_rng(3).normal(scale=3.0, size=(rows, cols))


@pytest.mark.parametrize(
    ("names", "taken"),
    [
        (["Height", "HeightTrace", "ZSensor"], "Height"),
        (["Phase", "HeightRetrace", "HeightTrace"], "HeightTrace"),
        (["x", "y", "HeightRetrace", "Phase"], "HeightRetrace"),
        (["Amplitude", "ZSensorRetrace", "Topography"], "Topography"),
        (["Amplitude", "ZSensorRetrace", "Z"], "ZSensorRetrace"),
        (["Current", "Z"], "Z"),
        (["Current", "Z forward", "Z backward"], "Z forward"),
        (["height_retrace", "phase_trace"], "height_retrace"),
    ],
)
def test_default_channel_takes_the_height_channel(names: list[str], taken: str) -> None:
    assert pick_channel(names, "Height", where="f") == taken


def test_a_named_channel_is_matched_and_a_missing_one_listed() -> None:
    assert pick_channel(["HeightRetrace", "Phase"], "phase", where="f") == "Phase"
    assert pick_channel(["Height Retrace"], "height_retrace", where="f") == "Height Retrace"
    with pytest.raises(ImageFileError, match=r"f: no channel 'Height' \(has: Phase, Current\)"):
        pick_channel(["Phase", "Current"], "Height", where="f")
    with pytest.raises(ImageFileError, match=r"no variable 'Phase' \(has: HeightRetrace\)"):
        pick_channel(["HeightRetrace"], "Phase", where="f", what="variable")


def test_afspm_netcdf4_height_retrace_is_read_by_default(tmp_path: Path) -> None:
    h = _heights()
    p = write_nc4(tmp_path / "afspm.nc", h * 1e-9, variables=("HeightRetrace", "Phase"))
    im = load_image(p)
    assert im.channel == "HeightRetrace"
    np.testing.assert_allclose(im.heights_nm, h, rtol=1e-12, atol=1e-12)


def test_asylum_zsensor_is_read_when_no_height_channel(tmp_path: Path) -> None:
    h = _heights()
    note = {"ScanSize": "3.2e-08", "ScanPoints": "32", "ScanLines": "24", "ScanRate": "2"}
    p = write_ibw(tmp_path / "z.ibw", {"ZSensorRetrace": h * 1e-9, "PhaseTrace": h}, note=note)
    im = load_image(p, pixel_size_nm=1.0)
    assert im.channel == "ZSensorRetrace"
    np.testing.assert_allclose(im.heights_nm, h, rtol=1e-6)


def test_measure_reports_the_channel_it_took(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tex = rough_texture((96, 96), pixel_size_nm=2.0, rng=np.random.default_rng(5))
    paths = []
    for name, img in (("a.nc", tex), ("b.nc", fourier_shift(tex, dx_px=2.0, dy_px=-1.0))):
        paths.append(write_nc4(tmp_path / name, img * 1e-9, variables=("HeightRetrace",)))
    capsys.readouterr()
    code = main(["measure", str(paths[0]), str(paths[1]), "--json"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert code == 0, doc
    assert doc["reference_channel"] == doc["current_channel"] == "HeightRetrace"
    assert "a.nc: read channel 'HeightRetrace' for 'Height'" in err
    assert doc["dx_px"] == pytest.approx(2.0, abs=0.1)

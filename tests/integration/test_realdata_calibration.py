"""Header calibration bounds on a real HS-AFM movie with one corrupted header field."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import pytest

from afmdrift.io import ImageFileError, load_stack

pytestmark = pytest.mark.realdata


def test_corrupted_asd_scan_range_is_refused_naming_the_field(
    tmp_path: Path, real_file: Callable[[str], Path]
) -> None:
    """Regression: x_nm corrupted to 2.14e9 gave a 10.7 mm pixel, 11 mm of drift, exit 0."""
    data = real_file("hsafm_sample_0.asd").read_bytes()
    fields = struct.pack("<4i", 200, 200, 100, 100)  # x_pixels, y_pixels, x_nm, y_nm
    at = data.find(fields)
    assert 0 < at < 200
    bad = data[:at] + struct.pack("<4i", 200, 200, 2_140_000_000, 100) + data[at + 16 :]
    p = tmp_path / "corrupt.asd"
    p.write_bytes(bad)
    with pytest.raises(
        ImageFileError, match=r"corrupt\.asd.*x_nm = 2140000000.*1\.07e\+07 nm per pixel"
    ):
        load_stack(p)

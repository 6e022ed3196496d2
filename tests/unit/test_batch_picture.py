"""The archive's picture (``OUT/archive.svg``): one row of three bars per
recording, failed ones in red, names escaped, values in the tooltips."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from afmdrift.batch import Result
from afmdrift.batch._summary import _nice, plot_archive

SVG = "{http://www.w3.org/2000/svg}"


def result(k: int, *, failed: bool = False) -> Result:
    if failed:
        return Result(recording=f"r{k}", status="failed", error=f"r{k}: truncated")
    return Result(
        recording=f"r{k}",
        status="done",
        frames=60,
        valid_frames=45,
        drift_x_nm=3.0 * k,
        drift_y_nm=4.0 * k,
        duration_s=120.0,
    )


def bars(path: Path) -> list[tuple[float, str, str]]:
    """(width, colour, tooltip) of every bar, panel by panel."""
    root = ET.parse(path).getroot()
    out = []
    for rect in root.iter(f"{SVG}rect"):
        title = rect.find(f"{SVG}title")
        if title is not None:
            out.append((float(rect.get("width", "nan")), rect.get("fill", ""), title.text or ""))
    return out


def test_a_row_of_three_bars_per_recording_with_failed_ones_in_red(tmp_path: Path) -> None:
    rows: list[Result | None] = [result(1), result(2, failed=True), result(3), None]
    names = ["a & b", "<bad>", "c", "not yet"]
    path = tmp_path / "archive.svg"
    plot_archive(path, rows, names)
    seen = bars(path)
    assert len(seen) == 3 * 3  # the unfinished recording is left out
    rate, total, share = seen[0:3], seen[3:6], seen[6:9]
    # total drift 5k nm over 2 min: 2.5k nm/min; the failed row has no bar
    assert [t for _, _, t in total] == ["a & b: 5 nm", "<bad>: failed", "c: 15 nm"]
    assert [t for _, _, t in rate] == ["a & b: 2.5 nm/min", "<bad>: failed", "c: 7.5 nm/min"]
    assert [c for _, c, _ in total] == ["#1f77b4", "#d62728", "#1f77b4"]
    assert total[1][0] == 0.0
    # bars scale with the value: c's total drift is three times a & b's
    assert total[2][0] == pytest.approx(3 * total[0][0], rel=0.01)
    assert share[0][2] == "a & b: 0.75"
    text = path.read_text(encoding="utf-8")
    assert "3 recordings (1 failed, in red)" in text
    # the names are escaped in the file (the parser above read them back)
    assert "a &amp; b" in text
    assert "&lt;bad&gt;" in text
    assert "not yet" not in text


def test_a_recording_with_no_drift_measured_has_no_drift_bar_not_a_zero(tmp_path: Path) -> None:
    """Regression (issue 37): a refusal is never a number, in the picture too."""
    none = Result(recording="n", status="no_drift", frames=2, valid_frames=0, duration_s=60.0,
                  error="no frame was measured")  # fmt: skip
    path = tmp_path / "archive.svg"
    plot_archive(path, [result(1), none], ["a", "n"])
    rate, total, share = bars(path)[0:2], bars(path)[2:4], bars(path)[4:6]
    assert total[1] == (0.0, "#7f7f7f", "n: no drift measured")
    assert rate[1][2] == "n: no drift measured"
    assert share[1][2] == "n: 0"
    assert "no drift measured</text>" in path.read_text(encoding="utf-8")


def test_an_empty_or_degenerate_archive_still_gives_a_picture(tmp_path: Path) -> None:
    path = tmp_path / "archive.svg"
    plot_archive(path, [None, None], ["a", "b"])
    assert bars(path) == []
    zero = Result(recording="z", status="done", frames=1, valid_frames=1, duration_s=0.0)
    plot_archive(path, [zero], ["z"])
    assert [w for w, _, _ in bars(path)] == [0.0, 0.0, pytest.approx(bars(path)[2][0])]
    assert bars(path)[2][0] > 0  # one valid frame of one: the whole share


@pytest.mark.parametrize(
    ("peak", "end"),
    [(26.0, 30.0), (0.7, 0.8), (1.0, 1.0), (101.0, 150.0), (0.0, 1.0), (math.nan, 1.0)],
)
def test_axes_end_at_a_round_value_above_the_largest_bar(peak: float, end: float) -> None:
    assert _nice(peak) == pytest.approx(end)

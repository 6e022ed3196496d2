"""``afmdrift demo``: the generated sequence is tracked and compared with the truth."""

from __future__ import annotations

import re

import pytest

from afmdrift.cli import main


def test_demo_prints_a_table_and_a_small_rms_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--frames", "5", "--size", "192"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if re.match(r"\s+\d+\s+\d+\s", line)]
    assert len(rows) == 5
    match = re.search(r"RMS error of cumulative drift: ([0-9.]+) nm", out)
    assert match is not None, out
    assert float(match.group(1)) < 0.2
    assert "4 measured frames; 0 rejected" in out


def test_demo_refuses_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--frames", "1"]) == 2
    assert "--frames" in capsys.readouterr().err

"""``afmdrift demo``: simulator, service and subscriber end with a summary naming the run."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from afmdrift.cli import main
from afmdrift.service import RunStore

pytestmark = pytest.mark.slow


def test_demo_runs_the_service_and_summarises_against_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "demo-run"
    assert main(["demo", "--frames", "6", "--size", "128", "--run-dir", str(run)]) == 0
    out = capsys.readouterr().out
    assert "served over a pseudo-terminal" in out
    assert "frames: 6 received by the subscriber, 6 in the run store" in out
    assert "offset error against truth: mean" in out
    assert "prediction error (made before each frame arrived)" in out
    assert f"run directory: {run}" in out
    with RunStore(run) as store:
        assert store.frame_count() == 6
        assert store.check_consistency() == []
    with (run / "measurements.csv").open(newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 6


def test_demo_refuses_a_bad_speed(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--speed", "0"]) == 2
    assert "--speed" in capsys.readouterr().err

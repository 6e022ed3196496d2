"""``afmdrift evaluate`` on a short simulated session: the registration engine, the
offset-move bookkeeping and every requested predictor, end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from afmdrift.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from afmdrift.drivers.sim._record import record_session

    out = tmp_path_factory.mktemp("eval") / "quiet"
    record_session("quiet-lab-24h", out, frames=16)
    return out


def test_evaluate_json_report(session_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(
        ["evaluate", str(session_dir), "--predictors", "last_value,kalman,physics", "--json"]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 16
    assert report["truth"] is True
    # The measured drift (image position + commanded offset) agrees with the truth:
    # guards the sign convention of drift_from_measurements end to end.
    for axis in ("x", "y"):
        assert report["measurement"]["vs_truth"][axis]["mean_abs_nm"] < 2.0
    assert list(report["predictors"]) == ["last_value", "kalman", "physics"]
    for r in report["predictors"].values():
        one = r["one_step"]["vs_measured"]
        assert one["n"] == report["valid_frames"] - report["skip"]
        assert 0 < one["x"]["mean_abs_nm"] <= one["x"]["rms_nm"] <= one["x"]["peak_nm"]
        assert set(r["continuous"]) == {"hermite", "sinc"}
        assert r["continuous"]["hermite"]["pooled"]["mean_abs_nm"] < 10.0
        assert r["timing_ms"]["per_frame_mean"] > 0


def test_evaluate_table_without_truth(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    copy = tmp_path / "no-truth"
    shutil.copytree(session_dir, copy)
    (copy / "truth.csv").unlink()
    assert main(["evaluate", str(copy), "--predictors", "constant_velocity"]) == 0
    out = capsys.readouterr().out
    assert "constant_velocity" in out
    assert "d(t) herm" not in out


def test_evaluate_unknown_predictor_is_reported(
    session_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["evaluate", str(session_dir), "--predictors", "kalman,crystal_ball"]) == 2
    err = capsys.readouterr().err
    assert "'crystal_ball'" in err
    assert "known: last_value" in err

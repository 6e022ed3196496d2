"""Drift logs (positions without images): read as they are, and taken by
``afmdrift evaluate`` and ``afmdrift diagnose`` like a session directory."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.session import SessionError, is_drift_log, read_drift_log

SHARED_LOGS = Path(__file__).resolve().parents[2].parent / "shared" / "validation" / "drift-logs"


def _log(path: Path, *, frames: bool = True, n: int = 40) -> Path:
    """A drift log of ``n`` frames 256 s apart: a steady drift plus a thermal
    response to a logged temperature, with frame 5 refused."""
    path.mkdir()
    t_start = 256.0 * np.arange(n)
    t_mid = t_start + 64.0
    temp_t = np.arange(0.0, 256.0 * n, 10.0)
    temp = 21.0 + 0.3 * np.sin(temp_t / 3000.0)
    drift = np.column_stack([0.01 * t_mid, -0.004 * t_mid]) + 5.0 * np.column_stack(
        [np.interp(t_mid, temp_t, temp) - 21.0, np.zeros(n)]
    )
    drift -= drift[0]
    rows = ["frame,t_s,x_nm,y_nm,sigma_nm,direction"]
    for k in range(n):
        if k == 5:
            continue
        rows.append(f"{k},{t_mid[k]},{drift[k, 0]},{drift[k, 1]},0.1,{'up' if k % 2 else 'down'}")
    if not frames:
        rows = [r.replace(",up", "").replace(",down", "") for r in rows]
        rows[0] = "frame,t_s,x_nm,y_nm,sigma_nm"
    (path / "positions.csv").write_text("\n".join(rows) + "\n")
    if frames:
        (path / "frames.csv").write_text(
            "frame,t_start_s,t_end_s\n"
            + "".join(f"{k},{t_start[k]},{t_start[k] + 128}\n" for k in range(n))
        )
    (path / "channels.csv").write_text(
        "t_s,temperature_c\n" + "".join(f"{a},{b}\n" for a, b in zip(temp_t, temp, strict=True))
    )
    (path / "events.csv").write_text("t_s,kind,x_nm,y_nm\n100.0,power_on,0,0\n")
    return path


def test_a_drift_log_is_read_with_its_frames_and_logs(tmp_path: Path) -> None:
    log = read_drift_log(_log(tmp_path / "log"))
    assert len(log) == 40
    assert np.isnan(log.xy_nm[5]).all()  # refused frame
    assert log.t_s[5] == pytest.approx(256.0 * 5 + 64.0)  # its window's middle
    assert log.sigma_nm[1] == pytest.approx(0.1)
    assert log.directions[1].value == "up"
    assert log.directions[2].value == "down"
    assert log.channels["temperature_c"].size == log.channel_t_s.size > 0
    assert [e.kind for e in log.events] == ["power_on"]
    assert log.truth is None
    assert is_drift_log(tmp_path / "log")


def test_directions_that_disagree_between_the_files_are_refused(tmp_path: Path) -> None:
    path = _log(tmp_path / "log")
    frames = path / "frames.csv"
    lines = frames.read_text().splitlines()
    lines = [lines[0] + ",direction"] + [f"{line},up" for line in lines[1:]]
    frames.write_text("\n".join(lines) + "\n")
    with pytest.raises(SessionError, match=r"frame 0 is 'down' here but 'up' in frames\.csv"):
        read_drift_log(path)


def test_a_log_without_frames_makes_each_position_a_frame(tmp_path: Path) -> None:
    log = read_drift_log(_log(tmp_path / "log", frames=False))
    assert len(log) == 39
    assert np.all(log.frame_times[:, 0] == log.t_s)
    assert np.all(np.isfinite(log.xy_nm))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("t_s,x_nm", "time,x_nm"), "t_s"),
        (lambda t: t.replace(",0.1,up", ",abc,up", 1), "sigma_nm"),
        (lambda t: t.replace("\n39,", "\n99,"), "frame 99 is not in frames.csv"),
        (lambda t: t.replace(",0.1,up", ",-0.1,up", 1), "must not be negative"),
        (lambda t: t.replace(",up\n", ",sideways\n", 1), "direction must be"),
    ],
)
def test_a_bad_drift_log_is_refused_naming_the_problem(
    tmp_path: Path, edit: object, message: str
) -> None:
    path = _log(tmp_path / "log")
    pos = path / "positions.csv"
    pos.write_text(edit(pos.read_text()))  # type: ignore[operator]
    with pytest.raises(SessionError, match=message):
        read_drift_log(path)


def test_evaluate_and_diagnose_take_a_drift_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _log(tmp_path / "log")
    assert main(["evaluate", str(path), "--predictors", "last_value,physics", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 40
    assert report["valid_frames"] == 39
    physics = report["predictors"]["physics"]["one_step"]["vs_measured"]
    last = report["predictors"]["last_value"]["one_step"]["vs_measured"]
    # the log's drift is a trend plus a thermal response: the physics model
    # predicts it far better than holding the last value
    assert physics["x"]["rms_nm"] < 0.5 * last["x"]["rms_nm"]
    code = main(["diagnose", str(path), "--effects", "trend,thermal", "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] == 39  # the frames with a position


@pytest.mark.realdata
@pytest.mark.parametrize(
    "name",
    sorted(p.name for p in SHARED_LOGS.iterdir() if p.is_dir()) if SHARED_LOGS.is_dir() else ["-"],
)
def test_the_shared_drift_logs_are_read_as_they_are(name: str) -> None:
    path = SHARED_LOGS / name
    if not path.is_dir():
        pytest.skip(f"shared drift logs not found at {SHARED_LOGS}")
    if not is_drift_log(path):
        pytest.skip(f"{name}: not a drift log folder")
    log = read_drift_log(path)
    answer = json.loads((path / "answer.json").read_text())
    assert len(log) == 112
    assert log.truth is not None
    assert set(log.channels) == {"temperature_c", "humidity_pct", "pressure_hpa"}
    assert np.isfinite(log.xy_nm).all(axis=1).sum() >= 100
    assert answer["hidden_effect"]  # the answer travels with the log, unread by afmdrift

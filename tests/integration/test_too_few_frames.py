"""A recording too short for the result asked is an error (exit status 1), not a
table of NaN: ``diagnose``, ``evaluate`` and ``replay`` on a two-frame session,
as a user runs them (a subprocess)."""

from __future__ import annotations

import dataclasses
import subprocess
from pathlib import Path

import numpy as np
import pytest
from service_sim import run_afmdrift, scenario_data, write_scenario

from afmdrift.diagnostics._diagnose import MIN_DIAGNOSE_FRAMES
from afmdrift.runs import MIN_REPLAY_FRAMES, RunStore
from afmdrift.session import read_session, write_session


@pytest.fixture(scope="module")
def two_frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-frame session recorded by ``afmdrift sim record``; both frames valid."""
    tmp = tmp_path_factory.mktemp("short")
    # two frames of 128² px, one every 32 s
    write_scenario(tmp / "two.toml", scenario_data(extra={"duration_s": 64.0}))
    done = run_afmdrift("sim", "record", "two.toml", "--out", "s", "--seed", "5", cwd=tmp)
    assert done.returncode == 0, done.stderr
    assert len(read_session(tmp / "s")) == 2
    return tmp / "s"


@pytest.fixture(scope="module")
def one_valid(two_frames: Path) -> Path:
    """The same session with its second frame blank: one valid measurement."""
    session = read_session(two_frames, mmap=False)
    frames = np.array(session.frames, dtype=np.float64)
    frames[1] = 0.0
    return write_session(dataclasses.replace(session, frames=frames), two_frames.with_name("blank"))


def _too_few(done: subprocess.CompletedProcess[str], valid: int, needed: int) -> None:
    assert done.returncode == 1, done.stderr
    assert f"too few frames: {valid} valid, {needed} needed" in done.stderr
    assert "Traceback" not in done.stderr
    assert "nan" not in done.stdout.lower()


def test_diagnose_of_two_frames_is_an_error_not_a_finding_over_no_test(
    two_frames: Path,
) -> None:
    done = run_afmdrift("diagnose", str(two_frames), "--workers", "1", cwd=two_frames.parent)
    _too_few(done, 2, MIN_DIAGNOSE_FRAMES)
    assert "Nothing is missing" not in done.stdout


def test_evaluate_of_two_frames_is_an_error_not_a_table_of_nan(two_frames: Path) -> None:
    done = run_afmdrift("evaluate", str(two_frames), cwd=two_frames.parent)
    _too_few(done, 2, 3)  # one-step errors are scored from valid frame 2 (--skip) on
    done = run_afmdrift("evaluate", str(two_frames), "--skip", "1", "--predictors",
                     "last_value", cwd=two_frames.parent)  # fmt: skip
    assert done.returncode == 0, done.stderr


def test_evaluate_refuses_skip_0_where_nothing_predicts_the_first_frame(
    two_frames: Path,
) -> None:
    done = run_afmdrift("evaluate", str(two_frames), "--skip", "0", cwd=two_frames.parent)
    assert done.returncode == 2
    assert "--skip must be >= 1" in done.stderr
    assert "Traceback" not in done.stderr


def test_replay_of_one_valid_frame_writes_the_run_and_exits_1(one_valid: Path) -> None:
    run = one_valid.with_name("run")
    done = run_afmdrift("replay", str(one_valid), "--out", str(run), cwd=one_valid.parent)
    _too_few(done, 1, MIN_REPLAY_FRAMES)
    assert "prediction error" not in done.stdout
    assert f"run directory: {run}" in done.stdout
    with RunStore(run) as store:
        assert len(store.frames()) == 2
    assert (run / "measurements.csv").is_file()


def test_replay_of_two_valid_frames_gives_its_one_prediction_error(two_frames: Path) -> None:
    run = two_frames.with_name("run2")
    done = run_afmdrift("replay", str(two_frames), "--out", str(run), cwd=two_frames.parent)
    assert done.returncode == 0, done.stderr
    assert "prediction error mean" in done.stdout
    assert "nan" not in done.stdout

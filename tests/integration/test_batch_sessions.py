"""``afmdrift batch --task replay | diagnose`` on recorded sessions: the same
files as ``afmdrift replay`` and ``afmdrift diagnose``, through the runs layer,
on a worker that never loads the daemon."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from service_sim import run_afmdrift

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small session recorded with ``afmdrift sim record`` (channels, events, truth)."""
    root = tmp_path_factory.mktemp("recorded")
    done = run_afmdrift("sim", "record", "default", "--frames", "14", "--out", "sess", cwd=root)
    assert done.returncode == 0, done.stderr
    return root / "sess"


def test_batch_replay_writes_what_afmdrift_replay_writes(session: Path, tmp_path: Path) -> None:
    """One worker replays the session into OUT/<stem>/run, file for file what
    ``afmdrift replay`` writes; a stack given the same task is a failed row."""
    movie = tmp_path / "movie.npy"
    np.save(movie, np.random.default_rng(1).normal(size=(3, 64, 64)).astype(np.float32))
    out = tmp_path / "out"
    done = run_afmdrift("batch", str(session), str(movie), "--out", str(out), "--task", "replay",
                     "--pixel-size-nm", "1", "--workers", "1", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 1, done.stderr
    alone = run_afmdrift("replay", str(session), "--out", str(tmp_path / "alone"), cwd=tmp_path)
    assert alone.returncode == 0, alone.stderr
    for name in ("measurements.csv", "trajectory.csv", "trajectory_smoothed.csv"):
        ours = (out / "sess" / "run" / name).read_text(encoding="utf-8")
        assert ours == (tmp_path / "alone" / name).read_text(encoding="utf-8"), name
    with (out / "summary.csv").open(encoding="utf-8") as fh:
        rows = {row["recording"]: row for row in csv.DictReader(fh)}
    assert rows[str(session)]["status"] == "done"
    assert int(rows[str(session)]["frames"]) == 14
    failed = rows[str(movie)]
    assert failed["status"] == "failed"
    assert "needs a session directory" in failed["error"]
    assert "movie.npy" in failed["error"]


def test_a_diagnose_job_equals_afmdrift_diagnose_without_loading_the_daemon(
    session: Path, tmp_path: Path
) -> None:
    """A job run as a worker runs it writes ``afmdrift diagnose``'s JSON and
    text; neither the daemon (``afmdrift.service``) nor ZeroMQ is imported."""
    script = textwrap.dedent(
        f"""
        import json, sys
        from afmdrift.batch import Job, run_job
        from afmdrift.config import load_config

        job = Job(recording={str(session)!r}, path={str(session)!r},
                  out={str(tmp_path / "out")!r}, task="diagnose",
                  config=load_config(None).model_dump(mode="json"))
        result = run_job(job)
        loaded = sorted(m for m in sys.modules
                        if m.split(".")[0] == "zmq" or m.startswith("afmdrift.service"))
        print(json.dumps({{"status": result.status, "error": result.error, "loaded": loaded}}))
        """
    )
    ran = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=240
    )
    assert ran.returncode == 0, ran.stderr
    report = json.loads(ran.stdout.splitlines()[-1])
    assert report == {"status": "done", "error": "", "loaded": []}
    as_json = run_afmdrift("diagnose", str(session), "--json", cwd=tmp_path)
    as_text = run_afmdrift("diagnose", str(session), cwd=tmp_path)
    assert as_json.returncode == 0, as_json.stderr
    assert (tmp_path / "out" / "diagnosis.json").read_text(encoding="utf-8") == as_json.stdout
    assert (tmp_path / "out" / "diagnosis.txt").read_text(encoding="utf-8") == as_text.stdout
    assert (tmp_path / "out" / "report.html").stat().st_size > 0
    assert (tmp_path / "out" / "run" / "run.sqlite").is_file()

"""``afmdrift batch``'s progress line counts frames as the workers measure
or replay them, not only when a recording finishes: the workers report the
frames done to the run's own Dask event topic, and the client adds them to
the line."""

from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmdrift.batch import Result, _jobs, run_batch
from afmdrift.batch._jobs import Task
from afmdrift.batch._run import _Progress
from afmdrift.config import AfmdriftConfig
from afmdrift.testing import TextureShifter, rough_texture


def counts(text: str) -> list[tuple[int, int]]:
    """(recordings done, frames) of every state the line was drawn in."""
    return [(int(d), int(f)) for d, f in
            re.findall(r"(\d+)/\d+ recordings \(\d+ failed\), (\d+) frames", text)]  # fmt: skip


def in_process(
    recording: Path, out: Path, task: Task, pixel_size_nm: tuple[float, float] | None
) -> list[tuple[int, int]]:
    """``run_batch`` of one recording on an in-process worker (which reports
    after every frame when ``PROGRESS_INTERVAL_S`` is 0): the line's states."""
    from distributed import LocalCluster

    line = io.StringIO()
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as cluster:
        report = run_batch(
            [str(recording)],
            out,
            task=task,
            config=AfmdriftConfig(),
            scheduler=cluster.scheduler_address,
            pixel_size_nm=pixel_size_nm,
            progress=line,
        )
    assert [r.status for r in report.results] == ["done"]
    return counts(line.getvalue())


def test_the_line_adds_the_frames_the_workers_report_to_those_finished() -> None:
    out = io.StringIO()
    show = _Progress(out, total=2, done=0)
    show.event((0.0, {"out": "a", "frames": 10}))
    show.event((0.1, {"out": "b", "frames": 5}))
    show.event((0.2, {"out": "b", "frames": 7}))  # a later report replaces the earlier
    show.advance(Result(recording="a", status="done", frames=20), "a")
    show.event((0.3, {"out": "a", "frames": 12}))  # late: a is finished, ignored
    for bad in ((0.4, None), (0.5, {"out": "b"}), (0.6, {"out": "b", "frames": "x"}), "junk"):
        show.event(bad)  # type: ignore[arg-type]
    show.advance(Result(recording="b", status="failed", frames=9), "b")
    assert counts(out.getvalue()) == [(0, 10), (0, 15), (0, 17), (1, 27), (2, 29)]
    assert "(1 failed), 29 frames" in out.getvalue()


def test_a_worker_reports_frames_while_it_measures(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # an in-process worker, so that it reports after every frame
    monkeypatch.setattr(_jobs, "PROGRESS_INTERVAL_S", 0.0)
    rng = np.random.default_rng(4)
    shifter = TextureShifter(rough_texture((640, 640), pixel_size_nm=2.0, rng=rng))
    frames = np.stack([shifter.crop((512, 512), dx_px=0.7 * k, dy_px=0.3 * k) for k in range(40)])
    np.save(tmp_path / "movie.npy", frames.astype(np.float32))
    seen = in_process(tmp_path / "movie.npy", tmp_path / "out", "measure", (2.0, 2.0))
    assert seen[-1] == (1, 40)
    # frames counted before the recording finished, rising
    partial = [f for d, f in seen if d == 0]
    assert partial
    assert 0 < min(partial) < 40
    assert max(partial) <= 40
    assert partial == sorted(partial)


@pytest.mark.slow
def test_a_worker_reports_frames_while_it_replays_a_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "afmdrift", "sim", "record", "default", "--frames", "8",
         "--out", str(tmp_path / "sess")],
        capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    monkeypatch.setattr(_jobs, "PROGRESS_INTERVAL_S", 0.0)
    seen = in_process(tmp_path / "sess", tmp_path / "out", "replay", None)
    assert seen[-1] == (1, 8)
    partial = [f for d, f in seen if d == 0]  # before the session finished
    assert partial
    assert 1 <= partial[0] < 8
    assert partial[-1] <= 8
    assert partial == sorted(partial)

"""Dashboard parts without a browser: envelope, state, read-only store, server, CLI errors."""

from __future__ import annotations

import asyncio
import concurrent.futures
import gc
import json
import logging
import math
import os
import random
import sqlite3
import string
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.config import host_is_loopback as is_loopback
from afmdrift.dashboard import (
    ArrayTruth,
    Dashboard,
    DashboardError,
    Envelope,
    RunReader,
    RunState,
    StoreNotReadyError,
)
from afmdrift.pipeline import FrameRecord
from afmdrift.service import RunStore
from afmdrift.wire import FrameMsg, OffsetMsg

pytestmark = pytest.mark.timeout(60)


def _record(seq: int, *, t_s: float, x_nm: float, pred_x_nm: float = math.nan) -> FrameRecord:
    return FrameRecord(
        seq=seq,
        instrument_frame=seq,
        epoch=0,
        t_start_s=t_s - 8.0,
        t_end_s=t_s + 8.0,
        t_mid_s=t_s,
        direction="up",
        rows=64,
        cols=64,
        pixel_x_nm=2.0,
        pixel_y_nm=2.0,
        dx_nm=math.nan,
        dy_nm=math.nan,
        image_x_nm=x_nm,
        image_y_nm=0.0,
        x_nm=x_nm,
        y_nm=0.0,
        sigma_nm=0.1,
        valid=True,
        fed_model=True,
        reason="reference" if seq == 0 else "",
        valid_blocks=9,
        total_blocks=9,
        keyframe_index=0,
        reanchored=False,
        pred_x_nm=pred_x_nm,
        pred_y_nm=0.0 if math.isfinite(pred_x_nm) else math.nan,
        pred_sigma_nm=0.5 if math.isfinite(pred_x_nm) else math.nan,
        offset_x_nm=0.0,
        offset_y_nm=0.0,
        wall_s=1.0e9 + seq,
        latency_s=0.01,
        field_json="null",
    )


def _store(run_dir: Path, n: int) -> Path:
    with RunStore(run_dir) as store:
        for k in range(n):
            store.record_frame(
                _record(k, t_s=10.0 * k, x_nm=0.5 * k, pred_x_nm=0.5 * k + 0.2 if k else math.nan),
                predictor="constant_velocity",
                predictor_state={"name": "constant_velocity"},
                curve=None,
            )
    return run_dir


# --------------------------------------------------------------------------- envelope


def test_envelope_memory_is_bounded_over_24_h_and_keeps_the_extremes() -> None:
    env = Envelope(components=2, flags=2, capacity=256, initial_width_s=0.001)
    nbytes = env.nbytes()
    t = np.linspace(0.0, 86400.0, 200_001)
    for k, ts in enumerate(t):
        spike = 50.0 if k == 123_457 else 0.0
        env.add(float(ts), (math.sin(ts / 3600.0) + spike, -spike), (k % 1000 == 0, False))
    assert env.n_bins <= 256
    assert env.nbytes() == nbytes
    assert env.samples == t.size
    a = env.arrays()
    assert a["count"].sum() == t.size
    assert np.nanmax(a["max"][:, 0]) == pytest.approx(50.0 + math.sin(t[123_457] / 3600.0))
    assert np.nanmin(a["min"][:, 1]) == -50.0
    assert a["flag"][:, 0].sum() == 201  # every 1000th sample was flagged invalid
    assert a["flag"][:, 1].sum() == 0
    assert env.width_s * env.n_bins >= 86400.0


def test_envelope_counts_an_old_sample_in_its_bin_and_drops_one_before_the_start() -> None:
    env = Envelope(components=1, capacity=16, initial_width_s=1.0)
    env.add(5.5, (1.0,))
    env.add(7.5, (2.0,))
    env.add(5.9, (-3.0,))
    env.add(1.0, (9.0,))
    a = env.arrays()
    assert a["count"].tolist() == [2, 0, 1]
    assert a["min"][0, 0] == -3.0
    assert env.dropped == 1


def test_envelope_rejects_a_bad_capacity() -> None:
    with pytest.raises(ValueError, match="capacity"):
        Envelope(components=1, capacity=15)


# --------------------------------------------------------------------------- state


def _frame_msg(frame: int, *, t_s: float, x_nm: float | None, error: float | None) -> FrameMsg:
    return FrameMsg(
        seq=frame,
        frame=frame,
        instrument_frame=frame,
        t_s=t_s,
        wall_s=1.0e9,
        dx_nm=None,
        dy_nm=None,
        x_nm=x_nm,
        y_nm=0.0 if x_nm is not None else None,
        sigma_nm=0.1,
        valid=x_nm is not None,
        fed_model=True,
        reason="reference" if frame == 0 else "",
        valid_blocks=9,
        total_blocks=9,
        field=None,
        pred_x_nm=None,
        pred_y_nm=None,
        pred_error_nm=error,
        latency_s=0.01,
    )


def test_store_row_completes_the_wire_row_of_the_same_frame() -> None:
    state = RunState(max_frames=10)
    state.add_frame_msg(_frame_msg(3, t_s=30.0, x_nm=1.5, error=0.2))
    assert state.frames[3]["pred_sigma_nm"] is None
    state.add_records([_record(3, t_s=30.0, x_nm=1.5, pred_x_nm=1.3)])
    row = state.frames[3]
    assert row["pred_sigma_nm"] == 0.5
    assert row["stored"] is True
    assert len(state.frames) == 1


def test_a_frame_older_than_the_newest_is_put_in_order() -> None:
    state = RunState(max_frames=10)
    state.add_frame_msg(_frame_msg(5, t_s=50.0, x_nm=0.0, error=None))
    state.add_records([_record(0, t_s=0.0, x_nm=0.0), _record(3, t_s=30.0, x_nm=0.0)])
    assert list(state.frames) == [0, 3, 5]


def test_frames_are_a_ring_and_the_rolling_error_uses_the_window() -> None:
    state = RunState(max_frames=10, rolling_window=3)
    for k in range(25):
        state.add_frame_msg(_frame_msg(k, t_s=10.0 * k, x_nm=0.0, error=float(k)))
    assert list(state.frames) == list(range(15, 25))
    assert state.frames_dropped == 15
    assert state.frames[24]["roll_error_nm"] == pytest.approx((22 + 23 + 24) / 3)


def test_trend_says_worse_for_a_rising_error_and_steady_for_a_flat_one() -> None:
    rising = RunState(rolling_window=5)
    flat = RunState(rolling_window=5)
    for k in range(20):
        rising.add_frame_msg(_frame_msg(k, t_s=360.0 * k, x_nm=0.0, error=1.0 + 0.5 * k))
        flat.add_frame_msg(_frame_msg(k, t_s=360.0 * k, x_nm=0.0, error=2.0 + 0.01 * (k % 2)))
    up = rising.error_trend()
    assert up is not None
    assert up["word"] == "getting worse"
    assert up["nm_per_h"] == pytest.approx(5.0)
    steady = flat.error_trend()
    assert steady is not None
    assert steady["word"] == "steady"


def test_truth_is_zero_over_the_reference_frame() -> None:
    table = np.array([[0.0, 5.0, -2.0], [1000.0, 15.0, 8.0]])
    state = RunState(truth=ArrayTruth(table=table, label="test"))
    state.add_records([_record(0, t_s=100.0, x_nm=0.0), _record(1, t_s=200.0, x_nm=1.0)])
    _, points = state.take_new_truth()
    assert points[0] == [100.0, pytest.approx(0.0, abs=1e-9), pytest.approx(0.0, abs=1e-9)]
    assert points[-1] == [200.0, pytest.approx(1.0), pytest.approx(1.0)]
    assert len(points) == 1 + 8


def test_invalid_and_clamped_offsets_are_counted_per_bin() -> None:
    state = RunState()
    for k in range(10):
        state.add_offset(
            OffsetMsg(
                seq=k, t_s=0.01 * k, wall_s=1e9, x_nm=1.0, y_nm=2.0, valid=k >= 5, clamped=k == 7
            )
        )
    doc = state.offset_json()
    assert sum(doc["flags"][0]) == 5
    assert sum(doc["flags"][1]) == 1
    assert sum(doc["count"]) == 10
    json.dumps(doc, allow_nan=False)


def test_diagnosis_file_is_read_when_it_changes_and_bad_files_are_named(tmp_path: Path) -> None:
    from afmdrift.dashboard._sources import DiagnosisFile

    path = tmp_path / "diagnosis.json"
    diag = DiagnosisFile(path)
    assert diag.poll() is False
    assert "does not exist" in diag.note
    path.write_text("{not json", encoding="utf-8")
    assert diag.poll() is True
    assert diag.result is None
    assert "not readable as JSON" in diag.note
    path.write_text(json.dumps({"rmse_nm": 1.0}), encoding="utf-8")
    os.utime(path, ns=(1, 2))
    assert diag.poll() is True
    assert "not an afmdrift diagnose result" in diag.note
    path.write_text(json.dumps({"finding": "F", "config": "C"}), encoding="utf-8")
    os.utime(path, ns=(3, 4))
    assert diag.poll() is True
    assert diag.result is not None
    assert (diag.result["finding"], diag.result["config"]) == ("F", "C")
    assert diag.poll() is False


# --------------------------------------------------------------------------- store


def test_reader_reads_a_store_without_writing_it(tmp_path: Path) -> None:
    run = _store(tmp_path / "run", 5)
    before = (run / "run.sqlite").read_bytes()
    with RunReader(run) as reader:
        rows = reader.read_since(max_frames=3)
        assert [r.seq for r in rows.frames] == [2, 3, 4]
        assert rows.model is not None
        assert rows.model[1] == "constant_velocity"
        assert reader.session_reference() is not None
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            reader._db.execute("DELETE FROM frames")
    assert (run / "run.sqlite").read_bytes() == before


def test_reader_serves_threads_that_read_at_once(tmp_path: Path) -> None:
    # The dashboard polls the store, rebuilds d(t) from the stored curves and
    # draws the frame view in worker threads, all through one reader.
    run = _store(tmp_path / "run", 20)
    with RunReader(run) as reader:

        def hammer(k: int) -> int:
            n = 0
            for _ in range(150):
                if k % 3 == 0:
                    n += len(reader.read_since().frames)
                elif k % 3 == 1:
                    reader.stored_curves()
                    n += reader.session_reference() is not None
                else:
                    n += reader.frame(5) is not None
            return n

        with concurrent.futures.ThreadPoolExecutor(max_workers=6) as pool:
            counts = list(pool.map(hammer, range(6)))
    assert counts == [150 * 20, 150, 150] * 2


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        ("missing", "no such run directory"),
        ("empty", "not a run directory"),
        ("garbage", "not a usable run store"),
        ("version", "schema version '9' is not supported"),
    ],
)
def test_reader_refuses_bad_run_directories_with_one_line(
    tmp_path: Path, setup: str, message: str
) -> None:
    run = tmp_path / "run"
    if setup != "missing":
        run.mkdir()
    if setup == "garbage":
        (run / "run.sqlite").write_bytes(b"this is not a database" * 100)
    if setup == "version":
        _store(run, 1)
        db = sqlite3.connect(run / "run.sqlite")
        db.execute("UPDATE meta SET value = '9' WHERE key = 'schema_version'")
        db.commit()
        db.close()
    with pytest.raises(DashboardError, match=message) as info:
        RunReader(run)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "made",
    ["nothing", "directory", "empty file", "database without tables"],
)
def test_reader_tells_a_run_store_on_its_way_from_a_bad_one(tmp_path: Path, made: str) -> None:
    """The daemon creates the directory, then run.sqlite, then its tables:
    each stage before the last is "not ready" (a live dashboard waits), not
    an unusable store."""
    run = tmp_path / "run"
    if made != "nothing":
        run.mkdir()
    if made == "empty file":
        (run / "run.sqlite").touch()
    if made == "database without tables":
        db = sqlite3.connect(run / "run.sqlite")
        db.execute("PRAGMA journal_mode=WAL")
        db.close()
    with pytest.raises(StoreNotReadyError):
        RunReader(run)
    (run / "run.sqlite").unlink(missing_ok=True)
    _store(run, 1)
    with RunReader(run) as reader:
        assert reader.session_reference() is not None


def test_reader_calls_a_store_its_writer_holds_locked_not_ready(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon switches a new run.sqlite to WAL under an exclusive lock; a
    reader that waits past its busy timeout there (a slow disk) is told "not
    ready" (a live dashboard keeps waiting), not "not a usable run store"."""
    import afmdrift.dashboard._store as store_module

    monkeypatch.setattr(store_module, "_BUSY_TIMEOUT_S", 0.05)
    run = tmp_path / "run"
    run.mkdir()
    writer = sqlite3.connect(run / "run.sqlite", isolation_level=None)
    try:
        writer.execute("BEGIN EXCLUSIVE")
        with pytest.raises(StoreNotReadyError, match="locked") as info:
            RunReader(run)
        assert "\n" not in str(info.value)
    finally:
        writer.close()


def test_reader_calls_an_unusable_store_unusable_not_unready(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.sqlite").write_bytes(b"this is not a database" * 100)
    with pytest.raises(DashboardError, match="not a usable run store") as info:
        RunReader(run)
    assert not isinstance(info.value, StoreNotReadyError)


# --------------------------------------------------------------------------- server


def _silent_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{s.getsockname()[1]}"


async def _until(condition: Any, timeout_s: float = 10.0) -> None:
    """Wait until ``condition()`` holds; the dashboard's store poll changes it."""
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110 (polls as the dashboard's store poll does)
            await asyncio.sleep(0.02)


@pytest.mark.asyncio
async def test_live_dashboard_waits_for_the_run_directory_and_follows_the_run(
    tmp_path: Path,
) -> None:
    """Regression (issue 31): a dashboard started before the daemon ended with
    "no such run directory". It waits, says for what, on the page and in
    the first log line, and follows the run once the store appears, also
    through a half-made store (directory, then an empty file, then tables,
    then the instrument's identity in meta)."""
    run = tmp_path / "run"
    async with (
        Dashboard(
            run_dir=run,
            pub_endpoint=_silent_endpoint(),
            port=0,
            store_poll_s=0.05,
            wait_for_store=True,
        ) as dash,
        aiohttp.ClientSession() as http,
    ):
        waiting = dash.waiting_for_store
        assert waiting is not None
        assert str(run / "run.sqlite") in waiting
        assert "no such run directory" in waiting
        async with http.get(dash.url + "state.json") as resp:
            summary = await resp.json()
        assert summary["store_state"] == "waiting"
        assert summary["store_path"] == str(run / "run.sqlite")
        assert summary["store_note"] == waiting

        run.mkdir()
        await _until(lambda: "not a run directory" in (dash.waiting_for_store or ""))
        (run / "run.sqlite").touch()
        await _until(lambda: "no tables yet" in (dash.waiting_for_store or ""))
        assert dash.state.store_state == "waiting"

        _store(run, 3)
        await _until(lambda: len(dash.state.frames) == 3)
        assert dash.waiting_for_store is None
        assert dash.state.store_state == "open"
        assert dash.state.store_note == f"{run / 'run.sqlite'} (read-only)"
        with RunStore(run) as store:
            store.set_meta({"instrument_model": "a later fact"})
        await _until(lambda: "instrument_model" in dash.state.meta)


@pytest.mark.asyncio
async def test_a_run_directory_that_never_appears_is_repeated_in_the_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A mistyped --run-dir does not hang silently: the log says, again and
    again (every minute; here every 0.1 s), which path is still awaited."""
    import afmdrift.dashboard._app as app

    monkeypatch.setattr(app, "_STORE_WAIT_LOG_S", 0.1)
    run = tmp_path / "typo"
    caplog.set_level("WARNING", logger="afmdrift.dashboard")
    async with Dashboard(
        run_dir=run, pub_endpoint=_silent_endpoint(), port=0, store_poll_s=0.05, wait_for_store=True
    ):
        await _until(lambda: len(caplog.records) >= 2)
    for record in caplog.records[:2]:
        assert record.getMessage().startswith(
            f"still waiting for the run store {run / 'run.sqlite'} after "
        )
        assert "no such run directory" in record.getMessage()


@pytest.mark.asyncio
async def test_a_finished_run_is_not_waited_for(tmp_path: Path) -> None:
    with pytest.raises(DashboardError, match="no such run directory"):
        async with Dashboard(run_dir=tmp_path / "nope", port=0, wait_for_store=True):
            pass


def test_loopback_addresses() -> None:
    assert is_loopback("127.0.0.1")
    assert is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    assert not is_loopback("192.168.1.4")


def test_another_interface_needs_a_token(tmp_path: Path) -> None:
    with pytest.raises(DashboardError, match="needs an access token"):
        Dashboard(run_dir=_store(tmp_path / "run", 2), host="0.0.0.0")


@pytest.mark.asyncio
async def test_token_and_origin_are_checked(tmp_path: Path) -> None:
    token = "a-long-enough-test-token"
    async with (
        Dashboard(run_dir=_store(tmp_path / "run", 3), port=0, token=token) as dash,
        # unsafe: keep cookies of an IP-address host, as browsers do.
        aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http,
    ):
        base = dash.url.split("?")[0]
        async with http.get(base + "state.json") as resp:
            assert resp.status == 403
        async with http.get(base + "state.json", params={"token": "wrong" * 5}) as resp:
            assert resp.status == 403
        async with http.get(dash.url) as resp:
            assert resp.status == 200
            assert "plotly.min.js" in await resp.text()
        # The cookie set by the first visit is enough from now on.
        async with http.get(base + "state.json") as resp:
            assert resp.status == 200
            assert (await resp.json())["frames_kept"] == 3
        async with http.get(base + "ws", headers={"Origin": "http://evil.example"}) as resp:
            assert resp.status == 403
        async with http.ws_connect(base + "ws") as ws:
            first = await ws.receive_json(timeout=5)
            assert first["type"] == "snapshot"
            assert [r["seq"] for r in first["frames"]] == [0, 1, 2]


@pytest.mark.asyncio
async def test_a_page_that_falls_behind_is_dropped_and_the_others_keep_going(
    tmp_path: Path,
) -> None:
    async with (
        Dashboard(run_dir=_store(tmp_path / "run", 2), port=0, tick_s=60.0) as dash,
        aiohttp.ClientSession() as http,
        http.ws_connect(dash.url + "ws") as slow,
    ):
        assert (await slow.receive_json(timeout=5))["type"] == "snapshot"
        assert dash.pages == 1
        # More messages than a page's queue holds, with no chance to send any.
        for k in range(300):
            dash._broadcast({"type": "test", "k": k})
        assert dash.pages == 0
        async with http.ws_connect(dash.url + "ws") as fresh:
            assert (await fresh.receive_json(timeout=5))["type"] == "snapshot"
            dash._broadcast({"type": "test", "k": -1})
            assert (await fresh.receive_json(timeout=5)) == {"type": "test", "k": -1}
        received = 0
        while (msg := await slow.receive(timeout=5)).type == aiohttp.WSMsgType.TEXT:
            received += 1
        assert msg.type == aiohttp.WSMsgType.CLOSE
        assert (msg.data, msg.extra) == (4000, "too slow")
        assert received <= 256


@pytest.mark.asyncio
async def test_a_page_that_closes_while_a_large_message_is_sent_logs_no_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Regression (issue 42): a browser that went away while the dashboard sent
    it a large message (a frame view, a long run's snapshot) left a traceback
    in the dashboard's log. A browser offers compression; aiohttp compressed
    such a message in a task of its own, the page's writer was cancelled when
    the page closed, and that task then failed writing to the closed connection
    with no one to see it ("Task exception was never retrieved",
    ClientConnectionResetError). The end of the Chromium test, which closes
    the browser while frames keep coming, hit it now and then."""
    caplog.set_level(logging.ERROR)
    # Letters and digits: about 25 ms of compression, far longer than the close.
    pad = "".join(random.Random(42).choices(string.ascii_letters + string.digits, k=4_000_000))
    async with (
        Dashboard(run_dir=_store(tmp_path / "run", 2), port=0, tick_s=60.0) as dash,
        aiohttp.ClientSession() as http,
    ):
        for k in range(3):
            # compress=15: permessage-deflate offered, as browsers offer it.
            async with http.ws_connect(dash.url + "ws", compress=15) as page:
                assert (await page.receive_json(timeout=5))["type"] == "snapshot"
                dash._broadcast({"type": "test", "k": k, "pad": pad})
            # Leaving the block closed the page while the message was on its way.
            await _until(lambda: dash.pages == 0)
            await asyncio.sleep(0.2)
            gc.collect()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


@pytest.mark.asyncio
async def test_page_loads_nothing_from_outside(tmp_path: Path) -> None:
    async with (
        Dashboard(run_dir=_store(tmp_path / "run", 2), port=0) as dash,
        aiohttp.ClientSession() as http,
    ):
        for name in ("", "dashboard.js", "dashboard.css"):
            async with http.get(dash.url + name) as resp:
                text = await resp.text()
            assert "http://" not in text
            assert "https://" not in text
        async with http.get(dash.url + "plotly.min.js") as resp:
            assert resp.status == 200
            assert len(await resp.read()) > 1_000_000


# --------------------------------------------------------------------------- command line


def test_cli_unknown_run_dir_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dashboard", "--run-dir", str(tmp_path / "nope"), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"afmdrift: error: {tmp_path / 'nope'}: no such run directory"


def test_cli_following_a_daemon_waits_for_its_run_directory_and_says_so(
    tmp_path: Path,
) -> None:
    """Regression (issue 31): ``--run-dir RUN --pub ...`` started before the
    daemon ended with "no such run directory". It now serves, and its second
    line says which path it waits for (a wrong --run-dir shows there)."""
    import signal
    import subprocess
    import sys

    run = tmp_path / "not-yet"
    args = ["dashboard", "--run-dir", str(run), "--pub", _silent_endpoint(), "--port", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "afmdrift", *args],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first, second = proc.stdout.readline(), proc.stdout.readline()
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert first.startswith("afmdrift dashboard: http://127.0.0.1:"), (first, err)
    assert f"run directory {run}" in first
    assert second.startswith(f"afmdrift dashboard: waiting for {run / 'run.sqlite'} (")
    assert "no such run directory" in second
    assert proc.returncode == 0, err


def test_cli_corrupt_store_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.sqlite").write_bytes(b"\0garbage" * 512)
    assert main(["dashboard", "--run-dir", str(run), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("afmdrift: error: ")
    assert "not a usable run store" in err
    assert "\n" not in err


def test_cli_silent_endpoint_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp://127.0.0.1:{port}"
    assert main(["dashboard", "--pub", endpoint, "--port", "0", "--wait-s", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"afmdrift: error: no message from {endpoint} within 0.5 s: "
        "is afmdrift run publishing there?"
    )


def test_cli_bad_endpoint_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dashboard", "--pub", "nonsense", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("afmdrift: error: --pub 'nonsense': use tcp://HOST:PORT")
    assert "\n" not in err


def test_before_and_after_a_model_change_are_over_equal_numbers_of_frames() -> None:
    """Guards against comparing 20 frames before a change with the 3 after it
    (or the other way round): n grows with the frames after, up to 20."""
    from afmdrift.dashboard._live import change_effect

    rows = [{"seq": s, "pred_error_nm": 4.0} for s in range(30)]
    rows[7]["pred_error_nm"] = None  # no prediction: not counted
    assert change_effect(rows, 29) is None  # nothing predicted by the new model yet
    rows += [{"seq": 30, "pred_error_nm": 1.0}, {"seq": 31, "pred_error_nm": 2.0}]
    e = change_effect(rows, 29)
    assert e is not None
    assert e["frames"] == 2
    assert e["before_rms_nm"] == pytest.approx(4.0)
    assert e["after_rms_nm"] == pytest.approx(math.sqrt(2.5))
    assert e["ratio"] == pytest.approx(math.sqrt(2.5) / 4.0)
    rows += [{"seq": s, "pred_error_nm": 1.0} for s in range(32, 80)]
    e = change_effect(rows, 29)
    assert e is not None
    assert e["frames"] == 20
    # Only two frames before a change early in a run: two on each side.
    e = change_effect(rows, 1)
    assert e is not None
    assert e["frames"] == 2


def test_the_live_finding_offers_the_leading_significant_candidate_and_its_channel() -> None:
    """A named library term's logged channel (humidity -> humidity_pct) and a
    generic term's are found for the evidence plot; nothing significant offers nothing."""
    from afmdrift.dashboard._live import live_finding
    from afmdrift.wire import DiagnosisMsg

    def msg(candidates: list[dict[str, Any]]) -> DiagnosisMsg:
        return DiagnosisMsg(
            seq=0, wall_s=1.0, look=2, first_frame=0, last_frame=21, reason="every",
            duration_s=3.0,
            diagnosis={"plain_finding": "Missing: humidity.", "candidates": candidates,
                       "thresholds": {"alpha": 0.0015, "run_alpha": 0.01}},
        )  # fmt: skip

    named = {"term": "humidity", "effect": "humidity", "significant": True, "params": {}}
    generic = {"term": "channel:pressure_hpa", "significant": True,
               "params": {"channel": "pressure_hpa"}}  # fmt: skip
    weak = {"term": "creep", "significant": False, "params": {}}
    found = live_finding(msg([weak, named, generic]))
    assert found["candidate"]["term"] == "humidity"
    assert found["candidate"]["channel"] == "humidity_pct"
    assert found["plain_finding"] == "Missing: humidity."
    assert live_finding(msg([generic]))["candidate"]["channel"] == "pressure_hpa"
    assert live_finding(msg([weak]))["candidate"] is None

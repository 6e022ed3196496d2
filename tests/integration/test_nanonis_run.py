"""``afmdrift run --instrument nanonis://…`` against ``afmdrift sim serve --protocol nanonis``,
both as users run them: subprocesses, a real TCP port, a signal to stop."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import signal
import sqlite3
import sys
from pathlib import Path

import pytest
import zmq.asyncio

from afmdrift.client import Subscriber
from afmdrift.wire import ModelMsg, OffsetMsg

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service_sim import REPO, closed_port, scenario_data, write_scenario

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]


def _config(path: Path, run_dir: Path, pub_port: int, sim_port: int) -> Path:
    # The simulator takes any number of clients on its one port; the waits
    # get their own connection, as on a controller's second port.
    path.write_text(
        f"""
[driver]
nanonis_channel = 14
nanonis_clock_signal = "Clock (s)"
nanonis_wait_ms = 100
nanonis_wait_port = {sim_port}
nanonis_channels = {{temperature_c = "Temperature (C)", humidity_pct = "Humidity (%)"}}

[service]
run_dir = "{run_dir}"
pub_endpoint = "tcp://127.0.0.1:{pub_port}"
control_endpoint = "tcp://127.0.0.1:*"
frame_poll_interval_s = 0.05
clock_sync_interval_s = 0.1
channel_poll_interval_s = 0.2
event_poll_interval_s = 0.2
reconnect_delay_s = 0.1

[registration]
block_size = 32
extended_size = 64

[model]
predictor = "constant_velocity"
""",
        encoding="utf-8",
    )
    return path


def _frames(run_dir: Path) -> list[tuple[float, float]]:
    db_path = run_dir / "run.sqlite"
    if not db_path.is_file():
        return []
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)) as db:
            return db.execute("SELECT t_start_s, t_end_s FROM frames ORDER BY seq").fetchall()
    except sqlite3.OperationalError:
        return []


async def _stop(proc: asyncio.subprocess.Process) -> int:
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return await asyncio.wait_for(proc.wait(), 20)
        except TimeoutError:
            proc.kill()
    return await proc.wait()


async def test_afmdrift_run_records_frames_and_publishes_offsets(tmp_path: Path) -> None:
    scenario = write_scenario(tmp_path / "scenario.toml", scenario_data(seed=4, pixels=128))
    run_dir = tmp_path / "run"
    pub_port = closed_port()
    sim = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "afmdrift", "sim", "serve", "--protocol", "nanonis",
        "--port", "0", "--scenario", str(scenario), "--speed", "50",
        cwd=REPO, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    daemon: asyncio.subprocess.Process | None = None
    ctx = zmq.asyncio.Context()
    try:
        assert sim.stdout is not None
        port = int((await asyncio.wait_for(sim.stdout.readline(), 30)).decode().strip())
        cfg = _config(tmp_path / "afmdrift.toml", run_dir, pub_port, port)
        daemon = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "afmdrift", "run", "--config", str(cfg),
            "--instrument", f"nanonis://127.0.0.1:{port}",
            cwd=REPO, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        offsets: list[OffsetMsg] = []
        models: list[ModelMsg] = []
        async with Subscriber(f"tcp://127.0.0.1:{pub_port}", ctx=ctx) as sub:
            async with asyncio.timeout(120):
                while len(_frames(run_dir)) < 5 or not models or not any(o.valid for o in offsets):
                    assert daemon.returncode is None, "afmdrift run exited early"
                    msg = await sub.recv(timeout_s=30)
                    if isinstance(msg, OffsetMsg):
                        offsets.append(msg)
                    elif isinstance(msg, ModelMsg):
                        models.append(msg)
        assert await _stop(daemon) == 0
    finally:
        if daemon is not None and daemon.returncode is None:
            daemon.kill()
            await daemon.wait()
        await _stop(sim)
        ctx.term()
    frames = _frames(run_dir)
    assert len(frames) >= 5
    # frames every 32 s of instrument time (the scenario's frame period), each 16 s long
    periods = [b[1] - a[1] for a, b in itertools.pairwise(frames)]
    assert all(abs(p - 32.0) < 2.0 for p in periods), periods
    assert all(abs((e - s) - 16.0) < 1e-3 for s, e in frames)
    valid = [o for o in offsets if o.valid]
    assert valid
    assert all(abs(o.x_nm) < 100 and abs(o.y_nm) < 100 for o in valid)

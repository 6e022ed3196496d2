"""Fault injection: the daemon keeps running and its store stays consistent when the
simulator is killed and restarted, replies are corrupted or late, subscribers are
slow, the daemon itself is SIGKILLed, or the configuration is bad."""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import os
import random
import signal
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import pytest
import zmq
import zmq.asyncio
from service_sim import (
    SimProcess,
    committed_frames,
    driver,
    running_service,
    scenario_data,
    service_config,
    sim_server,
    small_scenario,
    write_scenario,
)

from afmdrift.client import Subscriber, control
from afmdrift.drivers import NanoScopeDriver
from afmdrift.drivers.sim._server import ServerFaults
from afmdrift.service import RunStore
from afmdrift.wire import OffsetMsg

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _check_store(run_dir: Path) -> list:  # type: ignore[type-arg]
    with RunStore(run_dir) as store:
        assert store.check_consistency() == []
        records = store.frames()
    assert [r.seq for r in records] == list(range(len(records)))
    keys = [(r.epoch, r.instrument_frame) for r in records]
    assert len(set(keys)) == len(keys), "a frame was recorded twice"
    t = [r.t_mid_s for r in records]
    assert all(b > a for a, b in itertools.pairwise(t)), "time axis not increasing"
    return records


@pytest.mark.asyncio
async def test_simulator_killed_and_restarted(tmp_path: Path) -> None:
    """The simulator process is SIGKILLed and started again on the same port with its
    clock back at 0: the daemon keeps running, flags the failure, and continues in a
    new epoch with a new reference."""
    ctx = zmq.asyncio.Context()
    run = tmp_path / "run"
    scenario = write_scenario(tmp_path / "scenario.toml", scenario_data())
    sim = SimProcess(scenario, speed=100.0)
    try:
        url = sim.start()
        async with running_service(service_config(run), driver(url), ctx) as service:
            async with asyncio.timeout(30):
                await service.wait_for_frames(4)
            sim.kill()
            async with asyncio.timeout(10):
                await service.wait_for_flag("instrument_error")
            before = service.frames_processed
            assert sim.start() == url
            async with asyncio.timeout(40):
                await service.wait_for_frames(before + 5)
            assert "instrument_error" not in service.status_msg().flags
    finally:
        sim.kill()
        ctx.term()
    records = _check_store(run)
    epochs = [r.epoch for r in records]
    assert epochs[0] == 0
    assert epochs[-1] == 1
    first_new = next(r for r in records if r.epoch == 1)
    assert first_new.reason == "new reference (position estimated)"
    assert all(r.fed_model for r in records if r.epoch == 1 and r.seq > first_new.seq)


@pytest.mark.asyncio
async def test_corrupted_bytes_and_timeouts_do_not_stop_the_service(tmp_path: Path) -> None:
    ctx = zmq.asyncio.Context()
    run = tmp_path / "run"
    try:
        async with (
            sim_server(small_scenario(), speed=20.0) as (server, url),
            running_service(service_config(run), driver(url), ctx) as service,
        ):
            async with asyncio.timeout(30):
                await service.wait_for_frames(2)
            server.faults.corrupt_next_reply(count=2, where="payload", match="FRAME:DATA")
            server.faults.corrupt_next_reply(count=3, where="header")
            server.faults.delay_next_reply(1.5, count=2, match="SYST:TIME")
            server.faults.truncate_next_reply(5, count=1, match="CHAN")
            async with asyncio.timeout(40):
                await service.wait_for_frames(service.frames_processed + 4)
            assert server.faults.pending == 0
            assert service.instrument_errors >= 3
    finally:
        ctx.term()
    records = _check_store(run)
    assert sum(r.fed_model for r in records) >= len(records) - 1


@pytest.mark.asyncio
async def test_slow_and_absent_subscribers_do_not_slow_the_offset_stream(tmp_path: Path) -> None:
    """A subscriber that never reads fills its queue and loses messages; the service
    and a well-behaved subscriber are unaffected."""
    ctx = zmq.asyncio.Context()
    try:
        async with sim_server(small_scenario(), speed=100.0) as (_, url):
            cfg = service_config(tmp_path / "run", offset_rate_hz=500.0, sndhwm=50)
            async with running_service(cfg, driver(url), ctx) as service:
                stuck = ctx.socket(zmq.SUB)
                stuck.setsockopt(zmq.RCVHWM, 10)
                stuck.setsockopt(zmq.SUBSCRIBE, b"")
                stuck.setsockopt(zmq.LINGER, 0)
                stuck.connect(service.pub_endpoint)
                good = Subscriber(service.pub_endpoint, topics=("offset",), ctx=ctx)
                try:
                    await asyncio.sleep(0.5)
                    seqs: list[int] = []
                    walls: list[float] = []
                    async with asyncio.timeout(20):
                        while len(seqs) < 1000:
                            msg = await good.recv()
                            assert isinstance(msg, OffsetMsg)
                            seqs.append(msg.seq)
                            walls.append(msg.wall_s)
                    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
                    rate = (len(seqs) - 1) / (walls[-1] - walls[0])
                    # A stream the stuck subscriber blocked would stall (no
                    # message once its queue is full); a busy machine only
                    # slows it a little (395/s of 500 was seen at a load of 9
                    # on 2 cores). The rate itself is bench_service's.
                    assert rate > 0.5 * 500.0
                    assert service.frames_processed > 0
                finally:
                    good.close()
                    stuck.close()
    finally:
        ctx.term()


def _write_config(path: Path, run_dir: Path, **service: object) -> Path:
    lines = ["[service]", f'run_dir = "{run_dir}"']
    base = {
        "pub_endpoint": "tcp://127.0.0.1:*",
        "control_endpoint": "tcp://127.0.0.1:*",
        "frame_poll_interval_s": 0.05,
        "clock_sync_interval_s": 0.1,
        "channel_poll_interval_s": 0.2,
        "event_poll_interval_s": 0.2,
        "reconnect_delay_s": 0.1,
    }
    base.update(service)
    for k, v in base.items():
        lines.append(f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v}")
    lines += ["[registration]", "block_size = 32", "extended_size = 64"]
    lines += ["[model]", 'predictor = "constant_velocity"']
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


async def _wait_frames(run_dir: Path, n: int, proc: asyncio.subprocess.Process) -> None:
    for _ in range(600):
        if committed_frames(run_dir) >= n:
            return
        assert proc.returncode is None, "daemon exited early"
        await asyncio.sleep(0.1)
    raise TimeoutError(f"fewer than {n} frames in {run_dir}")


async def _daemon(config: Path, url: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "afmdrift",
        "run",
        "--config",
        str(config),
        "--instrument",
        url,
        cwd=REPO,
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )


async def _reap(proc: asyncio.subprocess.Process) -> None:
    """Kill the daemon if a test left it running, and wait for it."""
    if proc.returncode is None:
        proc.kill()
        await proc.wait()


@pytest.mark.asyncio
async def test_sigkilled_daemon_resumes_its_model_and_reference(tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = _write_config(tmp_path / "svc.toml", run)
    async with sim_server(small_scenario(warmup_nm=(60.0, 30.0)), speed=50.0) as (_, url):
        url = f"socket://127.0.0.1:{url.rsplit(':', 1)[1]}"
        proc = await _daemon(cfg, url)
        try:
            await _wait_frames(run, 5, proc)
            proc.send_signal(signal.SIGKILL)
            assert await proc.wait() == -signal.SIGKILL
        finally:
            await _reap(proc)
        killed_at = _check_store(run)
        proc = await _daemon(cfg, url)
        try:
            await _wait_frames(run, len(killed_at) + 4, proc)
            proc.send_signal(signal.SIGTERM)
            assert await asyncio.wait_for(proc.wait(), 20) == 0
        finally:
            await _reap(proc)
    records = _check_store(run)
    resumed = records[len(killed_at)]
    # measured against the stored reference, by the stored model: no new reference
    assert resumed.reason == ""
    assert resumed.fed_model
    assert resumed.pred_x_nm == resumed.pred_x_nm  # not NaN: the model was restored
    assert abs(resumed.x_nm - resumed.pred_x_nm) < 3.0


@pytest.mark.parametrize(
    ("toml", "named"),
    [
        ("[service]\noffset_rate_hz = 5000\n", "service.offset_rate_hz"),
        ("[service]\nofset_rate_hz = 10\n", "service.ofset_rate_hz"),
        ('[service]\npub_endpoint = "tcp://*:5560"\n', "curve_secret_key_file"),
        ("[registration]\nblock_size = 4\n", "registration.block_size"),
    ],
)
def test_bad_configuration_exits_at_once_naming_the_key(
    tmp_path: Path, toml: str, named: str
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(toml, encoding="utf-8")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "afmdrift",
            "run",
            "--config",
            str(bad),
            "--instrument",
            "/dev/null",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONWARNINGS": "error"},
        check=False,
    )
    assert proc.returncode == 2
    assert named in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.asyncio
async def test_nan_frames_from_the_instrument_are_recorded_and_skipped(tmp_path: Path) -> None:
    """NaN pixels in frames coming from an instrument (here a replayed session) never
    stop the daemon or reach the model; the frames after them are measured normally."""
    import dataclasses

    import numpy as np

    from afmdrift.drivers.sim._record import record_session
    from afmdrift.service import open_instrument
    from afmdrift.session import read_session, write_session

    recorded = read_session(
        record_session(small_scenario(), tmp_path / "session", frames=8).path, mmap=False
    )
    frames = np.array(recorded.frames)
    frames[3, 40:60, 40:60] = np.nan
    frames[5, :, :] = np.nan
    nan_session = write_session(
        dataclasses.replace(recorded, frames=frames), tmp_path / "nan-session"
    )
    cfg = service_config(tmp_path / "run")
    cfg = cfg.model_copy(update={"driver": cfg.driver.model_copy(update={"replay_speed": 0.0})})
    ctx = zmq.asyncio.Context()
    try:
        instrument = open_instrument(cfg, url=f"replay:{nan_session}")
        async with running_service(cfg, instrument, ctx) as service:
            async with asyncio.timeout(60):
                await service.wait_for_frames(8)
            assert "low_confidence" not in service.status_msg().flags  # cleared by frame 7
    finally:
        ctx.term()
    records = _check_store(tmp_path / "run")
    assert len(records) == 8
    for k in (3, 5):
        assert not records[k].fed_model
        assert records[k].reason.startswith("registration failed")
    assert all(records[k].fed_model for k in (1, 2, 4, 6, 7))


async def _until(condition: Callable[[], bool], *, poll_s: float = 0.01) -> None:
    """Return once ``condition()`` holds (bound it with a timeout)."""
    for _ in itertools.count():
        if condition():
            return
        await asyncio.sleep(poll_s)


@pytest.mark.asyncio
async def test_offsets_turn_invalid_within_the_silence_limit_when_the_line_goes_dead(
    tmp_path: Path,
) -> None:
    """Regression: after the connection dropped, offsets stayed valid for about
    8 s (until the driver's own timeouts and retries gave up). Now they are
    invalid within service.instrument_silence_s (2 s) of the first unanswered
    request, whatever the driver's timeouts, and valid again once the
    instrument answers."""
    ctx = zmq.asyncio.Context()
    run = tmp_path / "run"
    cfg = service_config(run, instrument_silence_s=2.0)
    try:
        async with sim_server(small_scenario(), speed=20.0) as (server, url):
            # A driver slower to give up than the silence limit: only the
            # silence can make the offsets invalid in time.
            instrument = NanoScopeDriver(
                url, timeout_s=6.0, frame_timeout_s=6.0, reconnect_attempts=2
            )
            async with running_service(cfg, instrument, ctx) as service:

                def valid() -> bool:
                    return service.last_offset is not None and service.last_offset.valid

                async with asyncio.timeout(30):
                    await service.wait_for_frames(3)
                    await _until(valid)
                loop = asyncio.get_running_loop()
                server.faults.drop_next_reply(count=1_000_000)  # the line goes dead
                dead_at = loop.time()
                async with asyncio.timeout(10):
                    await _until(lambda: not valid())
                invalid_after_s = loop.time() - dead_at
                assert "instrument_silent" in service.status_msg().flags
                server.faults.clear()  # the instrument answers again
                async with asyncio.timeout(30):
                    await _until(valid)
    finally:
        ctx.term()
    # the clock is read every 0.1 s here: the first unanswered request comes at once
    assert invalid_after_s <= 2.5, invalid_after_s


async def _frames_in(
    tmp_path: Path, name: str, seconds: float, fault: Callable[[ServerFaults], None] | None
) -> tuple[float, int, int, list[str]]:
    """The share of the instrument's frames the daemon stores over ``seconds``
    (after its first frame), with ``fault`` applied to the simulator; also the
    records stored then, those held from the model and the warnings about the
    event log."""
    ctx = zmq.asyncio.Context()
    run = tmp_path / name
    handler = _Warnings()
    logging.getLogger("afmdrift").addHandler(handler)
    try:
        async with (
            sim_server(small_scenario(), speed=100.0) as (server, url),
            running_service(service_config(run), driver(url), ctx) as service,
        ):
            async with asyncio.timeout(30):
                await service.wait_for_frames(1)
            if fault is not None:
                fault(server.faults)
            first = service.frames_processed
            made0 = _instrument_frames(server)
            await asyncio.sleep(seconds)
            stored = service.frames_processed - first
            made = _instrument_frames(server) - made0
            server.faults.clear()
    finally:
        logging.getLogger("afmdrift").removeHandler(handler)
        ctx.term()
    records = _check_store(run)
    held = sum(r.reason.startswith("event log behind") for r in records)
    return stored / max(made, 1), stored, held, [m for m in handler.messages if "event log" in m]


def _instrument_frames(server: Any) -> int:
    """Frames the simulated instrument has completed so far."""
    frame = server.sim.latest_frame()
    return 0 if frame is None else int(frame.index) + 1


class _Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.mark.asyncio
async def test_a_lying_or_flooding_event_log_does_not_starve_the_frames(tmp_path: Path) -> None:
    """Regression: an event log that announced more entries than it sent let 4 frames
    be stored in 30 s (28 without the fault, 14 %); one that streamed without end,
    1 (4 %). Each now costs at most its bounded read per poll: the daemon stores
    most of the frames the instrument makes (on a quiet machine all of them;
    beside a two-process CPU hog 75 % with the lying log, the line's polls
    taking longer), and the fault is reported once, naming the instrument.
    Frames are counted against the instrument's own, so a busy machine does
    not make the healthy run the yardstick."""
    seconds = 6.0
    healthy, _, _, quiet = await _frames_in(tmp_path, "healthy", seconds, None)
    assert healthy >= 0.8, f"only {healthy:.0%} of the instrument's frames without a fault"
    assert quiet == []
    lying, _, held, said = await _frames_in(
        tmp_path, "lying", seconds, lambda f: f.overcount_event_log(3, count=10**6)
    )
    assert lying >= 0.5, (lying, healthy)
    assert held == 0  # the fence shows the log sent all it had: nothing is unknown
    assert len(said) == 1, said
    assert "announced" in said[0]
    assert "afmdrift SimulatedAFM" in said[0]  # the instrument is named
    flood, flood_frames, held, said = await _frames_in(
        tmp_path, "flood", seconds, lambda f: f.flood_event_log(count=10**6)
    )
    assert flood >= 0.5, (flood, healthy)
    assert held >= flood_frames - 1  # moves may hide in the unread entries: not fed to the model
    assert len(said) == 1, said
    assert "announced 1000000000 entries" in said[0]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _truth_error_nm(records: list, sim: Any) -> float:  # type: ignore[type-arg]
    """Largest distance of the stored drift positions from the simulator's
    true drift (both zero at the session reference)."""
    ref = records[0]
    x0, y0 = sim.truth_at(ref.t_mid_s)
    worst = 0.0
    for r in records:
        if r.valid and math.isfinite(r.x_nm):
            x, y = sim.truth_at(r.t_mid_s)
            worst = max(worst, math.hypot(r.x_nm - (x - x0), r.y_nm - (y - y0)))
    return worst


@pytest.mark.asyncio
async def test_a_frozen_daemon_resumes_at_once_and_its_offsets_stay_continuous(
    tmp_path: Path,
) -> None:
    """SIGSTOP for ten frame periods, then SIGCONT (a suspended VM): the daemon
    measures again within two frame periods, stores no frame twice, and the
    offset stream it publishes goes on without a step beyond its rate limit."""
    run = tmp_path / "run"
    pub = f"tcp://127.0.0.1:{_free_port()}"
    rate_limit = 50.0
    cfg = _write_config(
        tmp_path / "svc.toml", run, pub_endpoint=pub, max_offset_rate_nm_s=rate_limit
    )
    speed, period_s = 50.0, 32.0
    frame_wall_s = period_s / speed
    ctx = zmq.asyncio.Context()
    try:
        async with sim_server(small_scenario(frame_period_s=period_s), speed=speed) as (
            server,
            url,
        ):
            proc = await _daemon(cfg, url)
            sub = Subscriber(pub, topics=("offset",), ctx=ctx)
            offsets: list[OffsetMsg] = []

            async def collect() -> None:
                while True:
                    msg = await sub.recv()
                    assert isinstance(msg, OffsetMsg)
                    offsets.append(msg)

            collector = asyncio.create_task(collect())
            try:
                await _wait_frames(run, 6, proc)
                proc.send_signal(signal.SIGSTOP)
                await asyncio.sleep(10 * frame_wall_s)
                stopped_at = committed_frames(run)
                proc.send_signal(signal.SIGCONT)
                t_cont = asyncio.get_running_loop().time()
                await _wait_frames(run, stopped_at + 1, proc)
                resumed_after_s = asyncio.get_running_loop().time() - t_cont
                await _wait_frames(run, stopped_at + 4, proc)
                proc.send_signal(signal.SIGTERM)
                assert await asyncio.wait_for(proc.wait(), 20) == 0
            finally:
                collector.cancel()
                await asyncio.gather(collector, return_exceptions=True)
                sub.close()
                await _reap(proc)
            records = _check_store(run)
            truth_error = _truth_error_nm(records, server.sim)
    finally:
        ctx.term()
    assert resumed_after_s < 2 * frame_wall_s + 0.5, resumed_after_s
    seqs = [o.seq for o in offsets]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    for a, b in itertools.pairwise(o for o in offsets if o.valid):
        step = math.hypot(b.x_nm - a.x_nm, b.y_nm - a.y_nm)
        assert step <= rate_limit * max(b.t_s - a.t_s, 0.0) + 1e-6, (a, b)
    assert truth_error < 3.0


@pytest.mark.asyncio
async def test_killed_ten_times_the_store_stays_whole_and_the_position_follows_the_truth(
    tmp_path: Path,
) -> None:
    """SIGKILL at a random moment, restart on the same run directory, ten
    times: SQLite's integrity check passes each time, no frame is stored
    twice, and the stored positions stay on the simulator's true drift."""
    run = tmp_path / "run"
    cfg = _write_config(tmp_path / "svc.toml", run)
    rng = random.Random(42)
    async with sim_server(small_scenario(warmup_nm=(60.0, 30.0)), speed=50.0) as (server, url):
        for _ in range(10):
            before = committed_frames(run)
            proc = await _daemon(cfg, url)
            try:
                await _wait_frames(run, before + 2, proc)
                await asyncio.sleep(rng.uniform(0.0, 0.64))
                proc.send_signal(signal.SIGKILL)
                assert await proc.wait() == -signal.SIGKILL
            finally:
                await _reap(proc)
            with RunStore(run) as store:
                assert store.check_consistency() == []
        records = _check_store(run)
        truth_error = _truth_error_nm(records, server.sim)
    assert len(records) >= 20
    # every restart measured against the stored reference: one session reference
    assert [r.reason for r in records].count("reference") == 1
    assert not [r for r in records if "new reference" in r.reason]
    assert truth_error < 3.0


@pytest.mark.asyncio
async def test_a_flood_of_control_clients_neither_slows_the_frames_nor_goes_unanswered(
    tmp_path: Path,
) -> None:
    """Twenty clients asking ``status`` as fast as they can: frames keep at
    least 80 % of their rate without them, every request is answered, and the
    daemon's memory stays flat."""
    run = tmp_path / "run"
    control_ep = f"tcp://127.0.0.1:{_free_port()}"
    cfg = _write_config(tmp_path / "svc.toml", run, control_endpoint=control_ep)
    ctx = zmq.asyncio.Context()
    try:
        async with sim_server(small_scenario(), speed=50.0) as (_, url):
            proc = await _daemon(cfg, url)
            try:
                await _wait_frames(run, 3, proc)
                healthy = await _frame_rate(run, proc, 4.0)
                rss0 = psutil.Process(proc.pid).memory_info().rss
                answered = [0] * 20
                stop = asyncio.Event()
                clients = [
                    asyncio.create_task(_ask_status(ctx, control_ep, answered, k, stop))
                    for k in range(20)
                ]
                try:
                    flooded = await _frame_rate(run, proc, 4.0)
                    rss1 = psutil.Process(proc.pid).memory_info().rss
                finally:
                    stop.set()
                    await asyncio.gather(*clients)
                proc.send_signal(signal.SIGTERM)
                assert await asyncio.wait_for(proc.wait(), 20) == 0
            finally:
                await _reap(proc)
    finally:
        ctx.term()
    assert flooded >= 0.8 * healthy, (flooded, healthy)
    assert min(answered) >= 10, answered
    assert rss1 < rss0 * 1.2 + 20e6, (rss0, rss1)
    _check_store(run)


async def _frame_rate(run: Path, proc: asyncio.subprocess.Process, seconds: float) -> float:
    """Frames the daemon commits per second over ``seconds``."""
    n0 = committed_frames(run)
    await asyncio.sleep(seconds)
    assert proc.returncode is None, "daemon exited"
    return (committed_frames(run) - n0) / seconds


async def _ask_status(
    ctx: zmq.asyncio.Context, endpoint: str, answered: list[int], k: int, stop: asyncio.Event
) -> None:
    """Ask ``status`` until ``stop``; every request must be answered."""
    while not stop.is_set():
        reply = await control(endpoint, "status", timeout_s=10.0, ctx=ctx)
        assert reply.ok
        answered[k] += 1

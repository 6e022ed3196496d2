"""NanoScopeDriver ↔ simulated AFM over the real transports: loopback TCP and a pseudo-terminal."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import numpy as np
import pytest
import pytest_asyncio

from afmdrift.drivers import EventKind, Frame, Instrument
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers._protocol import (
    ChecksumError,
    InstrumentError,
    InstrumentTimeout,
    ProtocolError,
)
from afmdrift.drivers.sim import Scenario, SimulatedAFM
from afmdrift.drivers.sim._server import SimulatorServer

# 64×64 frames at 64 lines/s: about one frame per virtual second; at speed 20 one per 50 ms.
SPEED = 20.0
SCENARIO = {
    "name": "wire-test",
    "scan": {"pixels": [64, 64], "size_nm": [1000.0, 1000.0], "line_rate_hz": 64.0},
    "sample": {"map_px": 512},  # a small height map keeps construction fast
}


def _sim() -> SimulatedAFM:
    return SimulatedAFM(Scenario.model_validate(SCENARIO), seed=7)


@pytest_asyncio.fixture
async def server() -> AsyncIterator[SimulatorServer]:
    async with SimulatorServer(_sim(), speed=SPEED) as srv:
        yield srv


async def _url(server: SimulatorServer, kind: str) -> str:
    if kind == "tcp":
        return f"socket://127.0.0.1:{await server.start_tcp(0)}"
    return await server.start_pty()


@pytest_asyncio.fixture(params=["tcp", "pty"])
async def driver(
    request: pytest.FixtureRequest, server: SimulatorServer
) -> AsyncIterator[NanoScopeDriver]:
    url = await _url(server, request.param)
    drv = NanoScopeDriver(url, timeout_s=2.0, frame_timeout_s=5.0, backoff_initial_s=0.02)
    async with drv:
        yield drv


async def _wait_frame(driver: NanoScopeDriver, *, after: int = -1) -> Frame:
    for _ in range(500):
        frame = await driver.latest_frame()
        if frame is not None and frame.index > after:
            return frame
        await asyncio.sleep(0.02)
    raise AssertionError(f"no frame after index {after} within 500 polls")


@pytest.mark.asyncio
async def test_identify_configure_scan_and_frame_equals_simulator(
    driver: NanoScopeDriver, server: SimulatorServer
) -> None:
    assert isinstance(driver, Instrument)
    info = await driver.identify()
    assert (info.vendor, info.model) == ("afmdrift", "SimulatedAFM")
    await driver.stop_scan()
    assert not await driver.scanning()
    await driver.configure_scan(size_nm=(800.0, 600.0), pixels=(48, 32), line_rate_hz=64.0)
    assert await driver.scan_size_nm() == (800.0, 600.0)
    assert await driver.pixels() == (48, 32)
    assert await driver.line_rate_hz() == 64.0
    t_start = await driver.now_s()
    before = await driver.frame_index()
    await driver.start_scan()
    assert await driver.scanning()
    first = await _wait_frame(driver, after=before)
    assert first.shape == (32, 48)
    assert first.t_start_s >= t_start - 1e-9
    assert first.pixel_size_nm == pytest.approx((800.0 / 48, 600.0 / 32))
    await driver.stop_scan()
    got = await driver.latest_frame()
    truth = server.sim.latest_frame()
    assert got is not None
    assert truth is not None
    assert got.index == truth.index
    np.testing.assert_array_equal(got.heights_nm, truth.heights_nm)
    assert (got.t_start_s, got.t_end_s, got.direction) == (
        truth.t_start_s,
        truth.t_end_s,
        truth.direction,
    )
    transfers = driver.frame_transfers
    assert await driver.latest_frame() is got  # cached: same index, no new transfer
    assert driver.frame_transfers == transfers


@pytest.mark.asyncio
async def test_offset_channels_events_and_clock(driver: NanoScopeDriver) -> None:
    t0 = await driver.now_s()
    await driver.set_offset(12.5, -4.0)
    assert await driver.get_offset() == pytest.approx((12.5, -4.0))
    await driver.set_offset(20.0, -4.0)
    ch = await driver.read_channels()
    assert set(ch.values) >= {"temperature_c", "humidity_pct"}
    assert 0.0 < ch.values["humidity_pct"] < 100.0
    events = await driver.events(0)
    assert events[0].kind is EventKind.POWER_ON
    moves = [e for e in events if e.kind is EventKind.OFFSET_MOVE]
    assert [(m.x_nm, m.y_nm) for m in moves][-2:] == [(12.5, -4.0), (7.5, 0.0)]  # deltas
    assert all(m.t_s >= t0 for m in moves)
    assert await driver.events(len(events)) == []
    assert await driver.event_count() == len(events)
    await driver.manipulate(10.0, 10.0, 30.0, 10.0)
    tail = await driver.events(len(events))
    assert [e.kind for e in tail] == [EventKind.MANIPULATION]
    assert await driver.now_s() > t0


@pytest.mark.asyncio
async def test_error_queue_and_invalid_commands(driver: NanoScopeDriver) -> None:
    assert await driver.next_error() == (0, "No error")
    with pytest.raises(InstrumentError) as info:
        await driver.query("NOT:A:COMMAND?")
    assert info.value.code == -113
    with pytest.raises(InstrumentError) as info:
        await driver.query("SCAN:OFFS 1")
    assert info.value.code == -109
    await driver.start_scan()
    with pytest.raises(InstrumentError) as info:
        await driver.configure_scan(line_rate_hz=10.0)
    assert info.value.code == -221
    await driver.stop_scan()
    with pytest.raises(InstrumentError) as info:
        await driver.configure_scan(pixels=(0, 64))
    assert info.value.code == -222
    codes = [(await driver.next_error())[0] for _ in range(5)]
    assert codes == [-113, -109, -221, -222, 0]


@pytest.mark.asyncio
async def test_tcp_server_restart_on_same_port_reconnects(server: SimulatorServer) -> None:
    port = await server.start_tcp(0)
    async with NanoScopeDriver(
        f"socket://127.0.0.1:{port}", timeout_s=1.0, backoff_initial_s=0.02
    ) as driver:
        t0 = await driver.now_s()
        await server.stop()
        assert await server.start_tcp(port) == port
        assert await driver.now_s() >= t0  # reconnected transparently
        assert server.connections == 2


@pytest.mark.asyncio
async def test_injected_disconnect_reconnects_and_repeats_query(server: SimulatorServer) -> None:
    port = await server.start_tcp(0)
    async with NanoScopeDriver(
        f"socket://127.0.0.1:{port}", timeout_s=1.0, backoff_initial_s=0.02
    ) as driver:
        server.faults.disconnect_on_next_reply(match="SCAN:OFFS")
        assert await driver.get_offset() == (0.0, 0.0)
        assert server.faults.applied == [("disconnect", "SCAN:OFFS")]
        assert server.connections == 2


@pytest.mark.asyncio
async def test_sequential_clients(server: SimulatorServer) -> None:
    url = f"socket://127.0.0.1:{await server.start_tcp(0)}"
    for _ in range(3):
        async with NanoScopeDriver(url, timeout_s=1.0) as driver:
            assert (await driver.identify()).model == "SimulatedAFM"
    assert server.connections == 3


@pytest.mark.asyncio
@pytest.mark.parametrize("kind", ["tcp", "pty"])
async def test_corrupted_frame_is_rejected_then_recovered(
    server: SimulatorServer, kind: str
) -> None:
    """Regression guard: an injected bit flip in a frame block never yields a frame."""
    url = await _url(server, kind)
    async with NanoScopeDriver(url, timeout_s=2.0, frame_timeout_s=5.0) as driver:
        frame = await _wait_frame(driver)
        await driver.stop_scan()
        server.faults.corrupt_next_reply(match="FRAME:DATA", where="payload", nbytes=3)
        with pytest.raises(ChecksumError):
            await driver.fetch_frame()
        again = await driver.fetch_frame()
        assert again is not None
        assert again.index >= frame.index
        truth = server.sim.latest_frame()
        assert truth is not None
        np.testing.assert_array_equal(again.heights_nm, truth.heights_nm)


@pytest.mark.slow
@pytest.mark.asyncio
async def test_late_dropped_partial_and_stale_replies(server: SimulatorServer) -> None:
    port = await server.start_tcp(0)
    # The server answers one connection's commands in order, so the reply after a
    # delayed one waits for it: the delay exceeds the timeout by a margin well below it.
    async with NanoScopeDriver(f"socket://127.0.0.1:{port}", timeout_s=1.0) as driver:
        server.faults.delay_next_reply(1.3, match="SYST:TIME")
        with pytest.raises(InstrumentTimeout):
            await driver.now_s()
        assert (await driver.identify()).model == "SimulatedAFM"  # late reply is skipped
        server.faults.drop_next_reply(match="SCAN:OFFS")
        with pytest.raises(InstrumentTimeout):
            await driver.get_offset()
        server.faults.truncate_next_reply(5, match="*IDN")
        with pytest.raises(InstrumentTimeout):
            await driver.identify()
        server.faults.stale_next_reply(match="SCAN:STAT")
        assert await driver.scanning()  # the repeated earlier reply is skipped
        assert driver.stale_replies == 2  # the late SYST:TIME reply and this one
        server.faults.corrupt_next_reply(match="SCAN:OFFS", where="header", nbytes=1)
        with pytest.raises(ProtocolError):
            await driver.get_offset()
        server.faults.corrupt_next_reply(match="EVENT:COUNT", where="header", nbytes=2)
        with pytest.raises(ProtocolError):
            await driver.event_count()
        assert await driver.get_offset() == (0.0, 0.0)
        assert server.faults.pending == 0


@pytest.mark.slow
@pytest.mark.asyncio
@pytest.mark.parametrize("kind", ["tcp", "pty"])
async def test_fault_storm_never_yields_a_wrong_frame(server: SimulatorServer, kind: str) -> None:
    """Random injected faults on frame and index replies: every call either raises a
    typed error or returns exactly the simulator's frame, and the line recovers."""
    url = await _url(server, kind)
    rng = np.random.default_rng(11)
    async with NanoScopeDriver(url, timeout_s=0.5, frame_timeout_s=0.5) as driver:
        await _wait_frame(driver)
        await driver.stop_scan()  # freeze the latest frame so it can be compared
        truth = server.sim.latest_frame()
        assert truth is not None
        outcomes = {"ok": 0, "error": 0}
        for _ in range(16):
            match = str(rng.choice(["FRAME:DATA", "FRAME:INDEX"]))
            fault = int(rng.integers(0, 4))
            if fault == 0:
                server.faults.corrupt_next_reply(match=match, nbytes=int(rng.integers(1, 4)))
            elif fault == 1:
                server.faults.truncate_next_reply(int(rng.integers(0, 200)), match=match)
            elif fault == 2:
                server.faults.stale_next_reply(match=match)
            else:
                server.faults.drop_next_reply(match=match)
            try:
                if match == "FRAME:DATA":
                    frame = await driver.fetch_frame()
                else:
                    frame = await driver.latest_frame()
            except (ProtocolError, InstrumentTimeout):
                outcomes["error"] += 1
            else:
                outcomes["ok"] += 1
                assert frame is not None
                assert frame.index == truth.index
                np.testing.assert_array_equal(frame.heights_nm, truth.heights_nm)
            server.faults.clear()
        assert outcomes["error"] > 0
        again = await driver.fetch_frame()
        assert again is not None
        np.testing.assert_array_equal(again.heights_nm, truth.heights_nm)


@pytest.mark.asyncio
async def test_concurrent_tasks_never_interleave_queries(driver: NanoScopeDriver) -> None:
    """Regression guard: the per-connection lock keeps each query with its own reply."""
    await driver.set_offset(3.0, -1.0)
    results = await asyncio.gather(
        *(driver.get_offset() for _ in range(10)),
        *(driver.pixels() for _ in range(10)),
        *(driver.latest_frame() for _ in range(5)),
        *(driver.read_channels() for _ in range(5)),
    )
    assert results[:10] == [(3.0, -1.0)] * 10
    assert results[10:20] == [(64, 64)] * 10
    assert driver.resyncs == 0
    assert driver.stale_replies == 0


@pytest.mark.asyncio
async def test_pty_client_leaving_mid_frame_does_not_poison_the_next_client(
    server: SimulatorServer,
) -> None:
    """A pty has no connections: a client that leaves before reading a frame block
    leaves it on the line. The next client skips or flushes it and gets correct replies."""
    path = await server.start_pty()
    async with NanoScopeDriver(path, timeout_s=2.0) as first:
        await _wait_frame(first)
        # Ask for a frame and the event log, then leave without reading the replies.
        await asyncio.to_thread(first.transport.write, b"@900 FRAME:DATA?\n@901 EVENT:LOG? 0\n")
        await asyncio.sleep(0.2)
    async with NanoScopeDriver(path, timeout_s=2.0) as second:
        try:
            info = await second.identify()
        except ProtocolError:
            info = await second.identify()  # the first try resynchronised the line
        assert info.model == "SimulatedAFM"
        frame = await second.fetch_frame()
        truth = server.sim.latest_frame()
        assert frame is not None
        assert truth is not None
        assert frame.index <= truth.index

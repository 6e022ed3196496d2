"""NanoScopeDriver against protocol tables (ScriptedTransport): every pair used, nothing left."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmdrift.drivers import EventKind, Frame, Instrument, ScanDirection
from afmdrift.drivers._nanoscope import MAX_EVENTS_PER_READ, NanoScopeDriver
from afmdrift.drivers._protocol import (
    ChecksumError,
    InstrumentDisconnected,
    InstrumentError,
    InstrumentTimeout,
    OutOfSequenceError,
    ProtocolError,
    encode_frame_reply,
)
from afmdrift.drivers._transport import ScriptedTransport

Pairs = Sequence[tuple[bytes | None, bytes]]


def _frame(index: int = 2) -> Frame:
    return Frame(
        index=index,
        heights_nm=np.arange(12, dtype=np.float32).reshape(3, 4) + index,
        pixel_size_nm=(2.0, 2.5),
        t_start_s=10.0 * index,
        t_end_s=10.0 * index + 6.0,
        direction=ScanDirection.DOWN,
    )


def _driver(pairs: Pairs, **kwargs: float) -> tuple[NanoScopeDriver, ScriptedTransport]:
    transport = ScriptedTransport(pairs)
    opts = {"timeout_s": 0.2, "frame_timeout_s": 0.2, "backoff_initial_s": 0.01, **kwargs}
    return NanoScopeDriver(transport, **opts), transport  # type: ignore[arg-type]


@pytest.mark.asyncio
async def test_driver_is_an_instrument() -> None:
    driver, _ = _driver([])
    assert isinstance(driver, Instrument)


@pytest.mark.asyncio
async def test_identify_time_channels_offset_table() -> None:
    driver, t = _driver(
        [
            (b"@1 *IDN?\n", b"@1 *IDN afmdrift,SimAFM,SN0001,1.0\n"),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 12.5\n"),
            (b"@3 CHAN?\n", b"@3 CHAN t=12.5,temperature_c=23.0,humidity_pct=40.5\n"),
            (b"@4 SCAN:OFFS 10.0,-2.5\n", b"@4 OK\n"),
            (b"@5 SCAN:OFFS?\n", b"@5 SCAN:OFFS 10.0,-2.5\n"),
        ]
    )
    async with driver:
        info = await driver.identify()
        assert (info.vendor, info.model, info.serial, info.firmware) == (
            "afmdrift",
            "SimAFM",
            "SN0001",
            "1.0",
        )
        assert await driver.now_s() == 12.5
        ch = await driver.read_channels()
        assert ch.t_s == 12.5
        assert dict(ch.values) == {"temperature_c": 23.0, "humidity_pct": 40.5}
        await driver.set_offset(10, -2.5)
        assert await driver.get_offset() == (10.0, -2.5)
    t.assert_done()


@pytest.mark.asyncio
async def test_scan_control_table() -> None:
    driver, t = _driver(
        [
            (b"@1 SCAN:SIZE 2000.0,1000.0\n", b"@1 OK\n"),
            (b"@2 SCAN:PIX 64,32\n", b"@2 OK\n"),
            (b"@3 SCAN:RATE 50.0\n", b"@3 OK\n"),
            (b"@4 SCAN:SIZE?\n", b"@4 SCAN:SIZE 2000.0,1000.0\n"),
            (b"@5 SCAN:PIX?\n", b"@5 SCAN:PIX 64,32\n"),
            (b"@6 SCAN:RATE?\n", b"@6 SCAN:RATE 50.0\n"),
            (b"@7 SCAN:START\n", b"@7 OK\n"),
            (b"@8 SCAN:STAT?\n", b"@8 SCAN:STAT RUN\n"),
            (b"@9 SCAN:STOP\n", b"@9 OK\n"),
            (b"@10 TIP:MOVE 1.0,2.0\n", b"@10 OK\n"),
            (b"@11 TIP:MAN 1.0,2.0,3.0,4.0\n", b"@11 OK\n"),
        ]
    )
    async with driver:
        await driver.configure_scan(size_nm=(2000, 1000), pixels=(64, 32), line_rate_hz=50)
        assert await driver.scan_size_nm() == (2000.0, 1000.0)
        assert await driver.pixels() == (64, 32)
        assert await driver.line_rate_hz() == 50.0
        await driver.start_scan()
        assert await driver.scanning()
        await driver.stop_scan()
        await driver.tip_move(1, 2)
        await driver.manipulate(1, 2, 3, 4)
    t.assert_done()


@pytest.mark.asyncio
async def test_event_log_table() -> None:
    driver, t = _driver(
        [
            (
                b"@1 EVENT:LOG? 1\n",
                b"@1 EVENT:LOG 1,2\n"
                b"@1 EVENT 1,5.0,offset_move,3.0,-1.0\n"
                b"@1 EVENT 2,9.5,manipulation,0.5,0.25\n",
            ),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 10.0\n"),  # the fence
            (b"@3 EVENT:LOG? 3\n", b"@3 EVENT:LOG 3,0\n"),
            (b"@4 SYST:TIME?\n", b"@4 SYST:TIME 10.5\n"),
            (b"@5 EVENT:COUNT?\n", b"@5 EVENT:COUNT 3\n"),
        ]
    )
    async with driver:
        events = await driver.events(1)
        assert [(e.t_s, e.kind, e.x_nm, e.y_nm) for e in events] == [
            (5.0, EventKind.OFFSET_MOVE, 3.0, -1.0),
            (9.5, EventKind.MANIPULATION, 0.5, 0.25),
        ]
        assert await driver.events(3) == []
        assert await driver.event_count() == 3
    t.assert_done()


@pytest.mark.asyncio
async def test_latest_frame_is_cached_by_index() -> None:
    """Regression guard: polling must not transfer the same frame block twice."""
    frame = _frame(2)
    driver, t = _driver(
        [
            (b"@1 FRAME:INDEX?\n", b"@1 FRAME:INDEX -1\n"),
            (b"@2 FRAME:INDEX?\n", b"@2 FRAME:INDEX 2\n"),
            (b"@3 FRAME:DATA?\n", encode_frame_reply(frame, tag=3)),
            (b"@4 FRAME:INDEX?\n", b"@4 FRAME:INDEX 2\n"),
        ]
    )
    async with driver:
        assert await driver.latest_frame() is None
        got = await driver.latest_frame()
        assert got is not None
        np.testing.assert_array_equal(got.heights_nm, frame.heights_nm)
        assert (got.index, got.t_start_s, got.t_end_s, got.direction) == (2, 20.0, 26.0, "down")
        assert await driver.latest_frame() is got
        assert driver.frame_transfers == 1
    t.assert_done()


@pytest.mark.asyncio
async def test_controller_error_reply_raises_instrument_error() -> None:
    driver, t = _driver(
        [
            (b"@1 BOGUS?\n", b'@1 ERR -113,"Undefined header"\n'),
            (b"@2 SYST:ERR?\n", b'@2 SYST:ERR -113,"Undefined header"\n'),
            (b"@3 SYST:ERR?\n", b'@3 SYST:ERR 0,"No error"\n'),
            (b"@4 SCAN:RATE 1000000.0\n", b'@4 ERR -222,"Data out of range"\n'),
            (b"@5 *CLS\n", b"@5 OK\n"),
        ]
    )
    async with driver:
        with pytest.raises(InstrumentError) as info:
            await driver.query("BOGUS?")
        assert info.value.code == -113
        assert await driver.next_error() == (-113, "Undefined header")
        assert await driver.next_error() == (0, "No error")
        with pytest.raises(InstrumentError, match="-222"):
            await driver.configure_scan(line_rate_hz=1e6)
        await driver.clear_errors()
    t.assert_done()


# --------------------------------------------------------------------------- bad replies


@pytest.mark.asyncio
async def test_late_reply_to_an_earlier_query_is_skipped() -> None:
    """A complete late reply (lower tag, e.g. after a timeout) is dropped, not taken as ours."""
    frame = _frame(1)
    driver, t = _driver(
        [
            (b"@1 SYST:TIME?\n", b""),
            (
                b"@2 SYST:TIME?\n",
                b"@1 SYST:TIME 1.0\n" + encode_frame_reply(frame, tag=1) + b"@2 SYST:TIME 2.0\n",
            ),
        ],
        timeout_s=0.1,
    )
    async with driver:
        with pytest.raises(InstrumentTimeout):
            await driver.now_s()
        assert await driver.now_s() == 2.0
        assert driver.stale_replies == 2
    t.assert_done()


@pytest.mark.asyncio
async def test_reply_with_a_future_tag_is_rejected_and_line_resynced() -> None:
    driver, t = _driver(
        [
            (b"@1 SYST:TIME?\n", b"@9 SYST:TIME 1.0\n@1 SYST:TIME 2.0\n"),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 3.0\n"),
        ]
    )
    async with driver:
        with pytest.raises(OutOfSequenceError):
            await driver.now_s()
        assert await driver.now_s() == 3.0
        assert driver.resyncs == 1
    t.assert_done()


@pytest.mark.asyncio
async def test_reply_with_wrong_header_is_out_of_sequence() -> None:
    driver, t = _driver([(b"@1 SCAN:OFFS?\n", b"@1 SCAN:SIZE 1.0,2.0\n")])
    async with driver:
        with pytest.raises(OutOfSequenceError):
            await driver.get_offset()
    t.assert_done()


@pytest.mark.asyncio
async def test_unsolicited_bytes_before_reply_are_rejected() -> None:
    driver, t = _driver(
        [
            (None, b"garbage\xff\n"),
            (b"@1 *IDN?\n", b"@1 *IDN a,b,c,d\n"),
            (b"@2 *IDN?\n", b"@2 *IDN a,b,c,d\n"),
        ]
    )
    async with driver:
        with pytest.raises(ProtocolError):
            await driver.identify()
        assert (await driver.identify()).model == "b"
    t.assert_done()


@pytest.mark.asyncio
@pytest.mark.parametrize(
    "reply",
    [
        b"@1 SYST:TIME abc\n",
        b"@1 SYST:TIME 1.0,2.0\n",
        b"@1 SYST:TIME nan\n",
        b"@1 SYST:TI\xffME 1\n",
        b"@1SYST:TIME 1\n",
    ],
)
async def test_garbled_replies_raise_protocol_error(reply: bytes) -> None:
    driver, t = _driver([(b"@1 SYST:TIME?\n", reply)])
    async with driver:
        with pytest.raises(ProtocolError):
            await driver.now_s()
    t.assert_done()


@pytest.mark.asyncio
async def test_partial_reply_times_out_and_is_flushed() -> None:
    driver, t = _driver(
        [
            (b"@1 SYST:TIME?\n", b"@1 SYST:TI"),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 4.0\n"),
        ]
    )
    async with driver:
        with pytest.raises(InstrumentTimeout):
            await driver.now_s()
        assert await driver.now_s() == 4.0
    t.assert_done()


@pytest.mark.asyncio
async def test_no_reply_times_out() -> None:
    driver, t = _driver([(b"@1 *IDN?\n", b"")])
    async with driver:
        with pytest.raises(InstrumentTimeout, match="timed out"):
            await driver.identify()
    t.assert_done()


@pytest.mark.asyncio
async def test_corrupted_frame_is_a_checksum_error_then_recovers() -> None:
    """Regression guard: a corrupted frame block is never returned as a frame."""
    good = _frame(5)
    bad = bytearray(encode_frame_reply(good, tag=2))
    bad[-3] ^= 0x40
    driver, t = _driver(
        [
            (b"@1 FRAME:INDEX?\n", b"@1 FRAME:INDEX 5\n"),
            (b"@2 FRAME:DATA?\n", bytes(bad)),
            (b"@3 FRAME:INDEX?\n", b"@3 FRAME:INDEX 5\n"),
            (b"@4 FRAME:DATA?\n", encode_frame_reply(good, tag=4)),
        ]
    )
    async with driver:
        with pytest.raises(ChecksumError):
            await driver.latest_frame()
        got = await driver.latest_frame()
        assert got is not None
        np.testing.assert_array_equal(got.heights_nm, good.heights_nm)
    t.assert_done()


@pytest.mark.asyncio
async def test_truncated_frame_block_times_out() -> None:
    data = encode_frame_reply(_frame(1), tag=1)
    driver, t = _driver([(b"@1 FRAME:DATA?\n", data[:-4])])
    async with driver:
        with pytest.raises(InstrumentTimeout):
            await driver.fetch_frame()
    t.assert_done()


@pytest.mark.asyncio
async def test_event_lines_out_of_order_are_rejected() -> None:
    driver, t = _driver(
        [
            (
                b"@1 EVENT:LOG? 0\n",
                b"@1 EVENT:LOG 0,2\n@1 EVENT 1,5.0,power_on,0.0,0.0\n"
                b"@1 EVENT 0,1.0,power_on,0.0,0.0\n",
            ),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 10.0\n"),
        ]
    )
    async with driver:
        with pytest.raises(ProtocolError, match="out of order"):
            await driver.events(0)
    t.assert_done()


# --------------------------------------------------------------------------- connection


class _FlakyTransport(ScriptedTransport):
    """Fails the first ``fail_opens`` opens, and drops the line on one chosen write."""

    def __init__(self, pairs: Pairs, *, fail_opens: int = 0, drop_on_write: int = -1) -> None:
        super().__init__(pairs)
        self.fail_opens = fail_opens
        self.drop_on_write = drop_on_write
        self.writes = 0

    def _open_raw(self) -> None:
        super()._open_raw()
        if self.opens <= self.fail_opens:
            raise InstrumentDisconnected(f"open {self.opens} refused")

    def _write_raw(self, data: bytes) -> None:
        self.writes += 1
        if self.writes == self.drop_on_write:
            raise InstrumentDisconnected("peer closed")
        super()._write_raw(data)


@pytest.mark.asyncio
async def test_connect_retries_with_backoff_then_succeeds() -> None:
    t = _FlakyTransport([(b"@1 *IDN?\n", b"@1 *IDN a,b,c,d\n")], fail_opens=2)
    driver = NanoScopeDriver(t, timeout_s=0.2, backoff_initial_s=0.01, reconnect_attempts=3)
    async with driver:
        assert (await driver.identify()).vendor == "a"
    assert t.opens == 3
    t.assert_done()


@pytest.mark.asyncio
async def test_connect_gives_up_after_bounded_attempts() -> None:
    t = _FlakyTransport([], fail_opens=10)
    driver = NanoScopeDriver(t, backoff_initial_s=0.01, reconnect_attempts=3)
    with pytest.raises(InstrumentDisconnected, match="after 3 attempt"):
        await driver.connect()
    assert t.opens == 3


@pytest.mark.asyncio
async def test_lost_line_reconnects_and_repeats_an_idempotent_query() -> None:
    t = _FlakyTransport([(b"@2 SYST:TIME?\n", b"@2 SYST:TIME 7.0\n")], drop_on_write=1)
    driver = NanoScopeDriver(t, timeout_s=0.2, backoff_initial_s=0.01)
    async with driver:
        assert await driver.now_s() == 7.0
    assert t.opens == 2
    t.assert_done()


@pytest.mark.asyncio
async def test_lost_line_does_not_repeat_a_manipulation() -> None:
    """Regression guard: a tip push must not be sent twice after a reconnect."""
    t = _FlakyTransport([], drop_on_write=1)
    driver = NanoScopeDriver(t, timeout_s=0.2, backoff_initial_s=0.01)
    async with driver:
        with pytest.raises(InstrumentDisconnected):
            await driver.manipulate(0, 0, 1, 1)
    assert t.opens == 2
    t.assert_done()


def test_driver_rejects_bad_options() -> None:
    with pytest.raises(ValueError, match="timeout_s"):
        NanoScopeDriver(ScriptedTransport([]), timeout_s=0)
    with pytest.raises(ValueError, match="reconnect_attempts"):
        NanoScopeDriver(ScriptedTransport([]), reconnect_attempts=0)


# --------------------------------------------------------------------------- fuzzing


_GOOD_FRAME = encode_frame_reply(_frame(3), tag=1)


@settings(max_examples=60, deadline=None)
@given(
    st.one_of(
        st.binary(max_size=200).map(lambda b: b + b"\n"),
        st.tuples(st.integers(0, len(_GOOD_FRAME) - 1), st.integers(1, 255)).map(
            lambda p: (
                _GOOD_FRAME[: p[0]] + bytes([_GOOD_FRAME[p[0]] ^ p[1]]) + _GOOD_FRAME[p[0] + 1 :]
            )
        ),
    )
)
def test_fuzz_driver_frame_query_raises_only_typed_errors(reply: bytes) -> None:
    """Random or bit-flipped bytes in answer to FRAME:DATA? give a typed error or the
    exact original frame, never another exception and never a wrong frame."""

    async def run() -> Frame | None:
        driver, _ = _driver([(b"@1 FRAME:DATA?\n", reply)], timeout_s=0.02)
        return await driver.fetch_frame()

    try:
        frame = asyncio.run(run())
    except (ProtocolError, InstrumentTimeout, InstrumentError):
        return
    if frame is not None:
        np.testing.assert_array_equal(frame.heights_nm, _frame(3).heights_nm)
        assert frame.t_start_s == _frame(3).t_start_s


@pytest.mark.asyncio
async def test_transport_factory_gives_a_fresh_transport_on_reconnect() -> None:
    made: list[_FlakyTransport] = []

    def factory() -> _FlakyTransport:
        if made:  # the replacement after the first line dropped
            made.append(_FlakyTransport([(b"@2 SYST:TIME?\n", b"@2 SYST:TIME 5.0\n")]))
        else:
            made.append(_FlakyTransport([], drop_on_write=1))
        return made[-1]

    driver = NanoScopeDriver(factory, timeout_s=0.2, backoff_initial_s=0.01)
    async with driver:
        assert await driver.now_s() == 5.0
    assert len(made) == 2  # one from the constructor, a fresh one on reconnect
    assert made[0].opens == 1
    made[-1].assert_done()


@pytest.mark.asyncio
async def test_event_log_announcing_more_than_it_sends_ends_at_the_fence(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Regression: such an instrument starved the daemon (4 frames stored in 30 s
    against 28), each read waiting out the driver's timeout for a line that never
    came. The fence query sent behind EVENT:LOG ends the read at once: the entry
    sent is taken, nothing is left behind, and the fault is reported once, naming
    the instrument."""
    short = b"@%d EVENT:LOG 0,5\n@%d EVENT 0,1.0,power_on,0.0,0.0\n"
    driver, t = _driver(
        [
            (b"@1 *IDN?\n", b"@1 *IDN ACME,AFM-9,SN42,1.0\n"),
            (b"@2 EVENT:LOG? 0\n", short % (2, 2)),
            (b"@3 SYST:TIME?\n", b"@3 SYST:TIME 10.0\n"),
            (b"@4 EVENT:LOG? 0\n", short % (4, 4)),
            (b"@5 SYST:TIME?\n", b"@5 SYST:TIME 10.5\n"),
        ]
    )
    caplog.set_level(logging.DEBUG, logger="afmdrift.drivers._nanoscope")
    async with driver:
        await driver.identify()
        started = time.monotonic()
        for _ in range(2):
            events = await driver.events(0)
            assert [(e.t_s, e.kind) for e in events] == [(1.0, EventKind.POWER_ON)]
            assert driver.event_backlog == 0
        assert time.monotonic() - started < driver.timeout_s  # never waited it out
    t.assert_done()
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1
    assert "ACME AFM-9 (serial SN42)" in warned[0].getMessage()
    assert "announced 5 entries from 0 but sent 1" in warned[0].getMessage()


@pytest.mark.asyncio
async def test_event_log_read_is_bounded_whatever_the_instrument_announces() -> None:
    """Regression: an instrument streaming 10^9 entries grew RSS without bound;
    one call reads at most MAX_EVENTS_PER_READ lines, the cursor goes on from there,
    the rest of the endless reply is dropped with the connection (reopened), and
    the backlog says the log is behind."""
    n = MAX_EVENTS_PER_READ + 50
    lines = b"".join(b"@1 EVENT %d,%d.0,power_on,0.0,0.0\n" % (i, i) for i in range(n))
    driver, t = _driver(
        [
            (b"@1 EVENT:LOG? 0\n", b"@1 EVENT:LOG 0,1000000000\n" + lines),
            (b"@2 SYST:TIME?\n", b"@2 SYST:TIME 10.0\n"),
            (
                b"@3 EVENT:LOG? %d\n" % MAX_EVENTS_PER_READ,
                b"@3 EVENT:LOG %d,1\n@3 EVENT %d,7.0,power_on,0.0,0.0\n"
                % (MAX_EVENTS_PER_READ, MAX_EVENTS_PER_READ),
            ),
            (b"@4 SYST:TIME?\n", b"@4 SYST:TIME 10.5\n"),
        ],
        event_budget_s=10.0,  # the bound under test is the line count
    )
    async with driver:
        first = await driver.events(0)
        assert len(first) == MAX_EVENTS_PER_READ
        assert driver.event_backlog == 1_000_000_000 - MAX_EVENTS_PER_READ
        opens = t.opens
        assert len(await driver.events(MAX_EVENTS_PER_READ)) == 1
        assert t.opens == opens + 1  # the line was reopened before the next query
        assert driver.event_backlog == 0

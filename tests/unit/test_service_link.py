"""The instrument link and acquisition: epochs, the event cursor, repeated frames.

A scripted instrument (the ``Instrument`` interface, as a device would answer)
drives the real :class:`InstrumentLink` and :class:`Acquisition`; each test
names the fault it guards against (issue "A daemon that cannot be knocked over").
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from afmdrift.config import ServiceConfig
from afmdrift.records import ChannelSample, Event, EventKind, Frame, InstrumentInfo
from afmdrift.service._acquire import Acquisition
from afmdrift.service._link import InstrumentDownError, InstrumentLink, every


class ScriptedInstrument:
    """An instrument whose clock, event log and frames the test sets."""

    def __init__(self) -> None:
        self.clock_s = 100.0
        self.log: list[Event] = []
        self.frame: Frame | None = None
        self.gate: asyncio.Event | None = None  # holds events() while set

    async def connect(self) -> None: ...

    async def close(self) -> None: ...

    async def identify(self) -> InstrumentInfo:
        return InstrumentInfo("test", "scripted", "0", "1")

    async def now_s(self) -> float:
        return self.clock_s

    async def latest_frame(self) -> Frame | None:
        return self.frame

    async def read_channels(self) -> ChannelSample:
        return ChannelSample(self.clock_s, {"temperature_c": 20.0})

    async def events(self, start: int = 0) -> list[Event]:
        entries = self.log[start:]
        if self.gate is not None:
            await self.gate.wait()
        return entries

    async def set_offset(self, x_nm: float, y_nm: float) -> None: ...

    async def get_offset(self) -> tuple[float, float]:
        return (0.0, 0.0)


async def _connected(inst: ScriptedInstrument) -> tuple[InstrumentLink, Acquisition]:
    link = InstrumentLink(inst, reconnect_delay_s=0.01, flags=set())
    acq = Acquisition(link, ServiceConfig())
    link.start()
    task = asyncio.create_task(link.connect_loop())
    await asyncio.wait_for(link.connected.wait(), 5.0)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    link.connected.set()
    return link, acq


def _move(t_s: float, x_nm: float) -> Event:
    return Event(t_s, EventKind.OFFSET_MOVE, x_nm, 0.0)


@pytest.mark.asyncio
async def test_restart_during_an_event_read_does_not_keep_the_old_cursor() -> None:
    """Regression: after an instrument restart the new epoch's event log was
    never read (the cursor was reset while a poll was in flight, then
    overwritten by it), so a later offset move was missed."""
    inst = ScriptedInstrument()
    inst.log = [_move(10.0, 1.0), _move(20.0, 2.0), _move(30.0, 3.0)]
    link, acq = await _connected(inst)
    inst.gate = asyncio.Event()
    poll = asyncio.create_task(acq.poll_events())
    await asyncio.sleep(0.01)  # the read of the old log is in flight
    inst.clock_s = 5.0  # the instrument restarted: a new, short log
    inst.log = [_move(1.0, 40.0)]
    await link.now_s()
    assert link.epoch == 1
    inst.gate.set()
    await poll
    assert acq.event_cursor == 0
    assert acq.events == []
    await acq.poll_events()
    assert acq.event_cursor == 1
    assert [e.x_nm for e in acq.events] == [40.0]


@pytest.mark.asyncio
async def test_clock_step_back_without_a_restart_does_not_replay_the_event_log() -> None:
    """Regression: a clock step back without a restart re-read the old event log
    and counted an offset move twice."""
    inst = ScriptedInstrument()
    inst.log = [_move(10.0, 5.0), _move(50.0, 7.0)]
    link, acq = await _connected(inst)
    await acq.poll_events()
    assert acq.event_cursor == 2
    inst.clock_s = 60.0  # stepped back from 100 s; the log is the same
    await link.now_s()
    assert link.epoch == 1
    inst.log.append(_move(70.0, 1.0))
    await acq.poll_events()
    assert [e.x_nm for e in acq.events] == [5.0, 7.0, 1.0]
    assert acq.event_cursor == 3


@pytest.mark.asyncio
async def test_a_restarted_instrument_s_new_log_is_read_from_the_start() -> None:
    inst = ScriptedInstrument()
    inst.log = [_move(10.0, 5.0)]
    link, acq = await _connected(inst)
    await acq.poll_events()
    inst.clock_s = 2.0
    inst.log = [_move(1.0, 9.0)]  # another log: a restart
    await link.now_s()
    await acq.poll_events()
    assert [e.x_nm for e in acq.events] == [5.0, 9.0]
    assert acq.events[1].t_s > acq.events[0].t_s  # one increasing time axis


@pytest.mark.asyncio
async def test_a_frame_ending_before_the_previous_one_is_reported_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Regression: such a frame was warned about on every poll (95 lines in 30 s)."""
    inst = ScriptedInstrument()
    image = np.zeros((8, 8))
    _, acq = await _connected(inst)
    inst.frame = Frame(
        index=5, t_start_s=80.0, t_end_s=90.0, heights_nm=image, pixel_size_nm=(1.0, 1.0)
    )
    await acq._poll_frame()
    assert acq.batches.qsize() == 1
    inst.frame = Frame(
        index=4, t_start_s=60.0, t_end_s=70.0, heights_nm=image, pixel_size_nm=(1.0, 1.0)
    )
    with caplog.at_level(logging.WARNING):
        for _ in range(20):
            await acq._poll_frame()
    assert caplog.text.count("ends before the previous one") == 1
    assert acq.batches.qsize() == 1


@pytest.mark.asyncio
async def test_frames_go_on_while_the_event_log_cannot_be_read() -> None:
    """Regression: an instrument whose event log could not be read (it announced
    more entries than it sent) stopped all frame processing while the status
    said running. Frames are now queued, held from the model with a reason,
    and the instrument_error flag stays up while the clock still answers."""
    inst = ScriptedInstrument()
    link, acq = await _connected(inst)

    async def broken(start: int = 0) -> list[Event]:
        raise TimeoutError("EVENT line 3 of 5 never came")

    inst.events = broken  # type: ignore[method-assign]
    image = np.zeros((8, 8))
    inst.frame = Frame(
        index=1, t_start_s=80.0, t_end_s=90.0, heights_nm=image, pixel_size_nm=(1.0, 1.0)
    )
    await acq._poll_frame()
    batch = acq.batches.get_nowait()
    assert batch.hold == "event log unreadable up to this frame"
    await link.now_s()  # another operation succeeds...
    assert "instrument_error" in link.flags  # ...but the event log still fails


@pytest.mark.asyncio
async def test_after_a_restart_the_service_clock_goes_on_without_freezing() -> None:
    """Regression: after an instrument restart the new epoch started where the
    last reading was, behind the time the offset stream had been publishing,
    so t_s stayed frozen (the clock never runs backwards) and the service
    stayed stale for as long as the outage lasted."""
    inst = ScriptedInstrument()
    link, _ = await _connected(inst)
    for k in range(4):  # an accelerated instrument: 100 s per wall second
        inst.clock_s = 100.0 + 5.0 * k
        await link.now_s()
        await asyncio.sleep(0.05)
    published_before = link.clock.at(time.time())
    assert published_before is not None
    await asyncio.sleep(0.3)  # the outage: about 30 instrument seconds go by
    published = link.clock.at(time.time())
    assert published is not None
    inst.clock_s = 2.0  # restarted
    t_new = await link.now_s()
    assert link.epoch == 1
    assert t_new >= published  # the axis goes on from what was published
    await asyncio.sleep(0.05)
    later = link.clock.at(time.time())
    assert later is not None
    assert later > t_new  # and keeps moving: no freeze


@pytest.mark.asyncio
async def test_a_late_schedule_counts_the_ticks_it_leaves_out() -> None:
    """Regression: ticks dropped after a lag over 50 ms left no trace; status now
    counts them (dropped_offset_ticks)."""
    skipped: list[int] = []
    ticks = 0

    async def body() -> None:
        nonlocal ticks
        ticks += 1
        if ticks == 3:
            time.sleep(0.3)  # noqa: ASYNC251 (the event loop blocked: 30 ticks of 10 ms go by)

    task = asyncio.create_task(every(0.01, body, catch_up_s=0.05, skipped=skipped.append))
    await asyncio.sleep(0.5)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert len(skipped) == 1
    assert 25 <= skipped[0] <= 35


class _Reconnecting:
    """A link whose connect loop runs, with the means to drop the connection."""

    def __init__(self, inst: ScriptedInstrument, **stored: object) -> None:
        self.link = InstrumentLink(inst, reconnect_delay_s=0.01, flags=set())
        if stored:
            self.link.resume(epoch=0, t_offset_s=0.0, last_seen_s=0.0, **stored)  # type: ignore[arg-type]
        self.changes: list[str] = []
        self.link.on_instrument_changed(self.changes.append)
        self.task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> _Reconnecting:
        self.link.start()
        self.task = asyncio.create_task(self.link.connect_loop())
        await asyncio.wait_for(self.link.connected.wait(), 5.0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.task is not None
        self.task.cancel()
        await asyncio.gather(self.task, return_exceptions=True)

    async def reconnect(self) -> None:
        async def lost() -> None:
            raise ConnectionError("the instrument went away")

        with pytest.raises(InstrumentDownError):
            await self.link.call(lost)
        await asyncio.wait_for(self.link.connected.wait(), 5.0)

    def frame(self, pixel_nm: float) -> None:
        self.link.frame_on_service_axis(
            Frame(0, np.zeros((8, 8)), (pixel_nm, pixel_nm), t_start_s=0.0, t_end_s=1.0)
        )


@pytest.mark.asyncio
async def test_another_instrument_on_the_connection_is_said_and_flagged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 42: another instrument took over the address (another serial)
    and the log said only 'connected to ... (serial 0002)'. A reconnection to
    the same instrument, or to one with new firmware, is no change."""
    inst = ScriptedInstrument()
    async with _Reconnecting(inst) as r:
        await r.reconnect()
        inst.identify = _identity("test", "scripted", "0", "2")  # type: ignore[method-assign]
        await r.reconnect()
        assert r.changes == []
        inst.identify = _identity("test", "scripted", "0002", "2")  # type: ignore[method-assign]
        with caplog.at_level(logging.WARNING):
            await r.reconnect()
    assert r.changes == ["test scripted (serial 0) -> test scripted (serial 0002)"]
    assert "instrument_changed" in r.link.flags
    assert "instrument changed: test scripted (serial 0) -> test scripted (serial 0002)" in (
        caplog.text
    )


@pytest.mark.asyncio
async def test_another_pixel_size_across_a_reconnection_is_another_calibration() -> None:
    """Issue 42: the same identity but another pixel size on the first frame
    after a reconnection is another instrument (or calibration); a pixel
    size that changes while connected is a zoom, not a change."""
    inst = ScriptedInstrument()
    async with _Reconnecting(inst) as r:
        r.frame(4.0)
        r.frame(2.0)  # zoomed in while connected
        await r.reconnect()
        r.frame(2.0)
        assert r.changes == []
        await r.reconnect()
        r.frame(3.0)
        r.frame(4.0)  # only the first frame after a connection is compared
    assert r.changes == ["test scripted (serial 0): pixel size 2 x 2 nm -> 3 x 3 nm "
                         "across a reconnection"]  # fmt: skip


@pytest.mark.asyncio
async def test_a_resumed_run_checks_the_instrument_it_was_recorded_with() -> None:
    """Issue 42: a restarted daemon compares the instrument with the one in
    its run store (identity, and the last frame's pixel size)."""
    stored = InstrumentInfo("test", "scripted", "0001", "1")
    async with _Reconnecting(ScriptedInstrument(), info=stored, pixel_size_nm=(4.0, 4.0)) as r:
        r.frame(4.0)
    assert r.changes == ["test scripted (serial 0001) -> test scripted (serial 0)"]
    same = InstrumentInfo("test", "scripted", "0", "1")
    async with _Reconnecting(ScriptedInstrument(), info=same, pixel_size_nm=(4.0, 4.0)) as r:
        r.frame(3.0)
    assert r.changes == ["test scripted (serial 0): pixel size 4 x 4 nm -> 3 x 3 nm "
                         "across a reconnection"]  # fmt: skip


def _identity(*fields: str) -> Callable[[], Awaitable[InstrumentInfo]]:
    async def identify() -> InstrumentInfo:
        return InstrumentInfo(*fields)

    return identify

"""Acquisition: frames, channels and events from the instrument, one batch per frame.

:class:`Acquisition` polls the instrument through the
:class:`~afmdrift.service._link.InstrumentLink` (so every time is already on
the service axis) and queues one :class:`FrameBatch` per new frame: the frame,
the event-log entries read up to it (every offset move up to the frame is
known), and the channel samples read since the previous batch. Polling goes on
while the worker processes a frame, so a frame that takes longer than the
frame period does not make the next one be missed.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass, field

from afmdrift.config import ServiceConfig
from afmdrift.drivers import EventBacklog
from afmdrift.records import ChannelSample, Event, EventKind, Frame, LoggedEvent
from afmdrift.service._link import InstrumentDownError, InstrumentLink, every

__all__ = ["Acquisition", "FrameBatch"]

log = logging.getLogger(__name__)

#: Frames waiting for the worker before the oldest is dropped (and logged).
_FRAME_QUEUE = 32
#: After a read that left the log further behind, the pause before the next one,
#: in units of that read's time: such a log has at most 1/(1 + _BEHIND_PAUSE) of the line.
_BEHIND_PAUSE = 9.0


@dataclass(slots=True)
class FrameBatch:
    """A new frame with what was logged since the previous batch."""

    frame: Frame
    detected_wall_s: float
    channels: list[ChannelSample] = field(default_factory=list)
    events: list[LoggedEvent] = field(default_factory=list)
    #: Why the frame must not feed the model (the event log up to it is unknown).
    hold: str | None = None


class Acquisition:
    """Polls frames, channels and events into :attr:`batches`.

    Attributes
    ----------
    batches : asyncio.Queue of FrameBatch
        New frames in order; when the worker falls ``_FRAME_QUEUE`` frames
        behind, the oldest frame is dropped (its channels and events are not).
    events : list of Event
        The whole event log read so far (service axis), for commanded offsets.
    event_cursor : int
        Next entry of the current epoch's event log to read.
    """

    def __init__(self, link: InstrumentLink, config: ServiceConfig) -> None:
        self.link = link
        self.config = config
        self.batches: asyncio.Queue[FrameBatch] = asyncio.Queue(maxsize=_FRAME_QUEUE)
        self.events: list[Event] = []
        self.event_cursor = 0
        self.frames_dropped = 0
        #: Entries the event log announced but the last read left (see EventBacklog).
        self.event_backlog = 0
        self._behind_until = -math.inf  # no event read before (loop time), while behind
        self._last_frame_key: tuple[int, float] | None = None
        self._channels: list[ChannelSample] = []
        self._events: list[LoggedEvent] = []
        self._event_lock = asyncio.Lock()
        #: Kind, x, y and raw instrument time of the last entry read.
        self._last_raw_event: tuple[EventKind | str, float, float, float] | None = None
        self._log_to_check: (
            tuple[int, tuple[EventKind | str, float, float, float] | None] | None
        ) = None
        self._ignored_key: tuple[int, float] | None = None
        link.on_epoch(self._new_epoch)

    def resume(
        self, *, events: list[Event], event_cursor: int, last_index: int, last_t_end_s: float
    ) -> None:
        """Continue after a restart: the event log and the last frame committed
        (its instrument index, and its end on the service axis)."""
        self.events = list(events)
        self.event_cursor = event_cursor
        self._last_frame_key = (last_index, last_t_end_s - self.link.t_offset_s)

    def _new_epoch(self, epoch: int, t_offset_s: float) -> None:
        # The instrument's clock went back. If it was restarted, its event log
        # starts afresh; if only its clock stepped, the log still holds what
        # was read. The next poll tells the two apart (_check_log_kept).
        self._log_to_check = (self.event_cursor, self._last_raw_event)
        self.event_cursor = 0
        self._last_frame_key = None
        self._ignored_key = None

    # ------------------------------------------------------------------ loops

    async def channel_loop(self) -> None:
        async def tick() -> None:
            self._channels.append(await self.link.read_channels())

        await every(self.config.channel_poll_interval_s, tick)

    async def event_loop(self) -> None:
        await every(self.config.event_poll_interval_s, self._poll_events_paced)

    async def _poll_events_paced(self) -> None:
        """A poll of the event loop. While the log is further behind than one read
        takes (a log that streams without end), the next read waits
        ``_BEHIND_PAUSE`` times as long as this one took, so that such a log
        has at most a tenth of the line (and feeds the worker at that pace);
        a log that catches up is polled as usual."""
        loop = asyncio.get_running_loop()
        if loop.time() < self._behind_until:
            return
        started = loop.time()
        read = await self.poll_events()
        if self.event_backlog > read:
            self._behind_until = loop.time() + _BEHIND_PAUSE * (loop.time() - started)
        else:
            self._behind_until = -math.inf

    async def poll_events(self) -> int:
        """Read the event log from the cursor; the cursor has one owner, this lock.
        Returns the number of entries read."""
        async with self._event_lock:
            epoch = self.link.epoch
            if self._log_to_check is not None:
                await self._check_log_kept()
            start = self.event_cursor
            entries = await self.link.events(start)
            if self.link.epoch != epoch:
                # The instrument restarted while this read was in flight: the
                # entries belong to no known epoch; the next poll starts over.
                return 0
            for k, e in enumerate(entries):
                self._events.append(LoggedEvent(epoch, start + k, e))
                self.events.append(e)
            if entries:
                last = entries[-1]
                self._last_raw_event = (
                    last.kind,
                    last.x_nm,
                    last.y_nm,
                    last.t_s - self.link.t_offset_s,
                )
            self.event_cursor = start + len(entries)
            instrument = self.link.instrument
            self.event_backlog = (
                instrument.event_backlog if isinstance(instrument, EventBacklog) else 0
            )
            return len(entries)

    async def _check_log_kept(self) -> None:
        """After an epoch: keep the cursor if the instrument's log still ends where
        the old one was read to (a clock step), else read the new log from 0."""
        assert self._log_to_check is not None
        cursor, last = self._log_to_check
        if cursor == 0 or last is None:
            self._log_to_check = None
            return
        entries = await self.link.events(cursor - 1)  # a failure: checked on the next poll
        self._log_to_check = None
        if entries:
            e = entries[0]
            raw_t_s = last[3]
            same = (e.kind, e.x_nm, e.y_nm) == last[:3]
            # Raw instrument times: the entry was logged at the same instrument
            # time whatever the service's shift is now.
            if same and abs((e.t_s - self.link.t_offset_s) - raw_t_s) < 1e-6:
                log.warning(
                    "instrument clock stepped back but its event log is the same; "
                    "reading on from entry %d",
                    cursor,
                )
                self.event_cursor = cursor

    async def frame_loop(self) -> None:
        await every(self.config.frame_poll_interval_s, self._poll_frame)

    async def _poll_frame(self) -> None:
        frame = await self.link.latest_frame()
        if frame is None:
            return
        key = (frame.index, frame.t_end_s)
        if key == self._last_frame_key:
            return
        if self._last_frame_key is not None and frame.t_end_s < self._last_frame_key[1]:
            # An older frame than the last one: the instrument was restarted
            # (its driver may have reconnected on its own). Read its clock.
            epoch = self.link.epoch
            await self.link.now_s()
            if epoch == self.link.epoch:
                if key != self._ignored_key:  # once per frame, not on every poll
                    log.warning("frame %d ends before the previous one; ignored", frame.index)
                    self._ignored_key = key
                return
        detected = time.time()
        if self._last_frame_key is not None and frame.index > self._last_frame_key[0] + 1:
            log.warning(
                "instrument frames %d..%d were replaced before they were read",
                self._last_frame_key[0] + 1,
                frame.index - 1,
            )
        hold = None
        if not self.event_backlog:
            # One bounded read, so every offset move up to this frame is known. A
            # log that is behind is left to the event loop: the frame does not wait.
            try:
                await self.poll_events()
            except InstrumentDownError:
                # The frame is still measured and recorded (nothing is lost), but
                # commanded moves may be missing from its drift position.
                hold = "event log unreadable up to this frame"
        if self.event_backlog:
            hold = f"event log behind: {self.event_backlog} announced entries not read yet"
        self._last_frame_key = key
        batch = FrameBatch(self.link.frame_on_service_axis(frame), detected, hold=hold)
        batch.channels, self._channels = self._channels, []
        batch.events, self._events = self._events, []
        if self.batches.full():
            dropped = self.batches.get_nowait()
            self.frames_dropped += 1
            log.warning(
                "processing is %d frames behind; frame %d dropped",
                self.batches.qsize() + 1,
                dropped.frame.index,
            )
            batch.channels[:0] = dropped.channels
            batch.events[:0] = dropped.events
        self.batches.put_nowait(batch)

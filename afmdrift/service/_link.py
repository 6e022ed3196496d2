"""The instrument link: connect, reconnect, epochs, and one time axis.

:class:`InstrumentLink` owns the connection to the instrument. It connects and
reconnects, counts failed calls, and puts every time the instrument reports on
the service's time axis, so nothing downstream ever sees an instrument time.

Failures (typed driver errors, OS errors, timeouts) do not stop the daemon:
the ``instrument_error`` flag is raised and a lost connection (or
``_FAILURES_BEFORE_RECONNECT`` failed calls in a row) is closed and reopened
after ``reconnect_delay_s``. An instrument whose clock went backwards was
restarted: the link starts a new *epoch*, shifts the instrument's times so the
service's time axis goes on from where its clock stands (through the outage,
increasing), and tells its listeners (who re-read the event log from the start
and take a new registration reference).

The link also checks that the instrument on the other end is still the one
it was (:meth:`InstrumentLink.on_instrument_changed`): another identity
(vendor, model or serial) when it (re)connects, or another calibration (the
pixel size of the first frame after a reconnection differs from the last
frame's before it) is logged as a warning, raises the ``instrument_changed``
flag and tells the listeners (who start a new chain of positions).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from afmdrift.drivers import Instrument
from afmdrift.errors import AfmdriftError
from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo
from afmdrift.service._safety import InstrumentClock

__all__ = ["INSTRUMENT_ERRORS", "InstrumentDownError", "InstrumentLink", "every"]

log = logging.getLogger(__name__)

#: Errors that mean "the instrument or its connection failed", not a bug.
INSTRUMENT_ERRORS: tuple[type[BaseException], ...] = (
    AfmdriftError,
    OSError,
    TimeoutError,
    EOFError,
)

#: Consecutive failed calls (garbled replies, timeouts) before a reconnect.
_FAILURES_BEFORE_RECONNECT = 3

_T = TypeVar("_T")

#: ``fn(info, t_s, offset_nm)``, called (and awaited if it returns an awaitable) on connect.
ConnectListener = Callable[[InstrumentInfo, float, tuple[float, float]], Any]

#: The fields of :class:`InstrumentInfo` that tell one instrument from another
#: (a firmware update leaves it the same instrument).
_IDENTITY_FIELDS = ("vendor", "model", "serial")


def _describe(info: InstrumentInfo) -> str:
    """``vendor model (serial S)``: the instrument as the log names it."""
    return f"{info.vendor} {info.model} (serial {info.serial})"


class InstrumentDownError(Exception):
    """An instrument call failed; the link's reconnect loop takes over."""


class InstrumentLink:
    """The daemon's one connection to the instrument.

    Parameters
    ----------
    instrument : Instrument
        Not yet connected.
    reconnect_delay_s : float
        Pause before each reconnection attempt.
    flags : set of str
        The service's status flags; the link raises and clears ``instrument_error``.

    Attributes
    ----------
    clock : InstrumentClock
        Instrument time (service axis) against wall time.
    epoch : int
        Instrument restarts seen (0 before the first).
    t_offset_s : float
        Added to every instrument time to place it on the service axis.
    connected : asyncio.Event
        Set while the connection is up.
    info : InstrumentInfo or None
        The identity of the instrument connected last (or of the one a
        resumed run was recorded with, until the first connection).
    """

    def __init__(
        self, instrument: Instrument, *, reconnect_delay_s: float, flags: set[str]
    ) -> None:
        self.instrument = instrument
        self.reconnect_delay_s = reconnect_delay_s
        self.flags = flags
        self.clock = InstrumentClock()
        self.epoch = 0
        self.t_offset_s = 0.0
        self.errors = 0
        self.connected = asyncio.Event()
        self._reconnect = asyncio.Event()
        self._failures = 0
        self._failing: set[str] = set()
        self._last_seen_s: float | None = None
        self._epoch_listeners: list[Callable[[int, float], None]] = []
        self._bugs_logged: set[tuple[str, str]] = set()
        self._connect_listeners: list[
            Callable[[InstrumentInfo, float, tuple[float, float]], Any]
        ] = []
        self._changed_listeners: list[Callable[[str], None]] = []
        self.info: InstrumentInfo | None = None
        # the pixel size of the last frame, and whether the next frame is the
        # first since a (re)connection (its pixel size is then checked)
        self._pixel_size_nm: tuple[float, float] | None = None
        self._check_calibration = False

    # ------------------------------------------------------------------ wiring

    def on_epoch(self, fn: Callable[[int, float], None]) -> None:
        """Call ``fn(epoch, t_offset_s)`` when the instrument was restarted."""
        self._epoch_listeners.append(fn)

    def on_connected(self, fn: Callable[[InstrumentInfo, float, tuple[float, float]], Any]) -> None:
        """Call ``fn(info, t_s, offset_nm)`` (awaited if it returns an awaitable) on each
        connection, with the instrument's time on the service axis and its XY offset."""
        self._connect_listeners.append(fn)

    def on_instrument_changed(self, fn: Callable[[str], None]) -> None:
        """Call ``fn(what)`` when the instrument is another one than before
        (``what`` says how, ``old -> new``)."""
        self._changed_listeners.append(fn)

    def resume(
        self,
        *,
        epoch: int,
        t_offset_s: float,
        last_seen_s: float,
        info: InstrumentInfo | None = None,
        pixel_size_nm: tuple[float, float] | None = None,
    ) -> None:
        """Continue the time axis of a run restored from the store, and check
        the instrument against the one it was recorded with (``info``, and
        the ``pixel_size_nm`` of its last frame)."""
        self.epoch = epoch
        self.t_offset_s = t_offset_s
        self._last_seen_s = last_seen_s
        self.info = info
        self._pixel_size_nm = pixel_size_nm

    def start(self) -> None:
        """Let :meth:`connect_loop` make the first connection."""
        self._reconnect.set()

    # ------------------------------------------------------------------ calls

    async def call(self, fn: Callable[..., Awaitable[_T]], *args: Any) -> _T:
        """Await ``fn(*args)`` on the connected instrument.

        Raises
        ------
        InstrumentDownError
            The call failed (the failure is counted and flagged).
        """
        await self.connected.wait()
        name = getattr(fn, "__name__", repr(fn))
        try:
            result = await fn(*args)
        except INSTRUMENT_ERRORS as err:
            self._failing.add(name)
            self._failed(fn, err)
            raise InstrumentDownError from err
        except Exception as err:
            # Not a failure an instrument is expected to have: its traceback
            # once (per call and kind), then handled as a failed call.
            key = (name, type(err).__name__)
            if key not in self._bugs_logged:
                self._bugs_logged.add(key)
                log.error("instrument call %s raised unexpectedly", name, exc_info=err)
            self._failing.add(name)
            self._failed(fn, err)
            raise InstrumentDownError from err
        self._failures = 0
        self._failing.discard(name)
        if not self._failing:
            # Cleared only when every operation that failed has worked again:
            # a clock that answers does not hide an event log that does not.
            self.flags.discard("instrument_error")
        return result

    async def now_s(self) -> float:
        """The instrument's clock on the service axis (a reading that went back starts an epoch)."""
        return self.observe_now(await self.call(self.instrument.now_s))

    async def read_channels(self) -> ChannelSample:
        sample = await self.call(self.instrument.read_channels)
        return ChannelSample(t_s=self.shift(sample.t_s), values=dict(sample.values))

    async def events(self, start: int) -> list[Event]:
        """Event-log entries ``start, start+1, ...``, on the service axis."""
        entries = await self.call(self.instrument.events, start)
        return [dataclasses.replace(e, t_s=self.shift(e.t_s)) for e in entries]

    async def latest_frame(self) -> Frame | None:
        """The last completed frame, in instrument time (see :meth:`frame_on_service_axis`)."""
        return await self.call(self.instrument.latest_frame)

    def frame_on_service_axis(self, frame: Frame) -> Frame:
        """``frame`` with its times on the service axis (and, the first frame
        after a connection, its pixel size checked against the last one's)."""
        self._see_calibration(frame.pixel_size_nm)
        shifted = dataclasses.replace(
            frame,
            t_start_s=self.shift(frame.t_start_s),
            t_end_s=self.shift(frame.t_end_s),
        )
        self._see(shifted.t_end_s)
        return shifted

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        await self.call(self.instrument.set_offset, x_nm, y_nm)

    def shift(self, t_s: float) -> float:
        return t_s + self.t_offset_s

    def silent_s(self) -> float:
        """Seconds the instrument has left a request unanswered, with no byte
        arriving (0 for instruments that cannot tell, and while it answers)."""
        if not self.connected.is_set():
            return math.inf if self._last_seen_s is not None else 0.0
        probe = getattr(self.instrument, "silent_s", None)
        return float(probe()) if callable(probe) else 0.0

    def see_frame_end(self, t_end_s: float) -> None:
        """A frame that ended at ``t_end_s`` (service axis) was processed."""
        self._see(t_end_s)

    # ------------------------------------------------------------------ connection

    def _failed(self, fn: Callable[..., Any], err: BaseException) -> None:
        """A failed call: a lost connection, or repeated errors, trigger a reconnect.

        A single garbled reply or timeout (the driver has already resynchronised
        the line) only skips this poll.
        """
        self._failures += 1
        self.errors += 1
        self.flags.add("instrument_error")
        name = getattr(fn, "__name__", fn)
        lost = isinstance(err, ConnectionError | EOFError) or (
            isinstance(err, OSError) and not isinstance(err, TimeoutError)
        )
        if not lost and self._failures < _FAILURES_BEFORE_RECONNECT:
            log.warning("instrument call %s failed: %s: %s", name, type(err).__name__, err)
            return
        if self.connected.is_set():
            log.warning(
                "instrument call %s failed: %s: %s; reconnecting", name, type(err).__name__, err
            )
        self.connected.clear()
        self._reconnect.set()

    async def connect_loop(self) -> None:
        """Connect, and reconnect whenever a call lost the connection."""
        first = True
        while True:
            await self._reconnect.wait()
            self._reconnect.clear()
            while True:
                if not first:
                    try:
                        await self.instrument.close()
                    except INSTRUMENT_ERRORS as err:
                        log.debug("close before reconnect: %s", err)
                    await asyncio.sleep(self.reconnect_delay_s)
                first = False
                try:
                    await self.instrument.connect()
                    info = await self.instrument.identify()
                    now = await self.instrument.now_s()
                    offset = await self.instrument.get_offset()
                except INSTRUMENT_ERRORS as err:
                    log.warning("instrument connection failed: %s: %s", type(err).__name__, err)
                    self.flags.add("instrument_error")
                    continue
                break
            t = self.observe_now(now)
            log.info(
                "connected to %s %s (serial %s, firmware %s) at t=%.3f s",
                info.vendor,
                info.model,
                info.serial,
                info.firmware,
                now,
            )
            self._see_identity(info)
            for fn in self._connect_listeners:
                result = fn(info, t, offset)
                if asyncio.iscoroutine(result):
                    await result
            self.flags.discard("instrument_error")
            self._failures = 0
            self._failing.clear()
            self.connected.set()

    async def close(self) -> None:
        try:
            await self.instrument.close()
        except INSTRUMENT_ERRORS as err:
            log.warning("closing the instrument failed: %s", err)

    # ------------------------------------------------------------------ identity

    def _see_identity(self, info: InstrumentInfo) -> None:
        """A connection to ``info``: another identity than before is a change;
        the same one has its calibration checked on its first frame."""
        old, self.info = self.info, info
        if old is not None and any(getattr(old, f) != getattr(info, f) for f in _IDENTITY_FIELDS):
            self._check_calibration = False  # another instrument: its frames differ anyway
            self._changed(f"{_describe(old)} -> {_describe(info)}")
        else:
            self._check_calibration = self._pixel_size_nm is not None

    def _see_calibration(self, pixel_size_nm: tuple[float, float]) -> None:
        """A frame of ``pixel_size_nm``: on the first after a connection,
        another pixel size than the last frame's is another calibration."""
        old, self._pixel_size_nm = self._pixel_size_nm, pixel_size_nm
        if not self._check_calibration or old is None:
            return
        self._check_calibration = False
        same = (math.isclose(a, b, rel_tol=1e-9) for a, b in zip(old, pixel_size_nm, strict=True))
        if not all(same):
            who = _describe(self.info) if self.info is not None else "the instrument"
            self._changed(
                f"{who}: pixel size {old[0]:.6g} x {old[1]:.6g} nm -> "
                f"{pixel_size_nm[0]:.6g} x {pixel_size_nm[1]:.6g} nm across a reconnection"
            )

    def _changed(self, what: str) -> None:
        self.flags.add("instrument_changed")
        log.warning(
            "instrument changed: %s; its positions start a new chain, and the "
            "difference is not taken for drift",
            what,
        )
        for fn in self._changed_listeners:
            fn(what)

    # ------------------------------------------------------------------ time axis

    def observe_now(self, now_s: float) -> float:
        """Record an instrument clock reading; a clock that went back starts an epoch.

        Returns the reading on the service's time axis.
        """
        wall = time.time()
        if self._last_seen_s is not None and now_s + self.t_offset_s < self._last_seen_s - 1e-6:
            self._new_epoch(now_s, wall)
        t = now_s + self.t_offset_s
        self.clock.observe(wall_s=wall, instrument_s=t)
        self._see(t)
        return t

    def _see(self, t_s: float) -> None:
        if self._last_seen_s is None or t_s > self._last_seen_s:
            self._last_seen_s = t_s

    def _new_epoch(self, now_s: float, wall_s: float) -> None:
        assert self._last_seen_s is not None
        self.epoch += 1
        # The restarted instrument's reading ``now_s`` is placed where the
        # service's clock stands now: the offset stream kept counting time
        # through the outage, and a new axis that started behind it would
        # freeze the published t_s (the clock never runs backwards) and keep
        # the service stale for as long as the outage lasted. And never
        # earlier than last-seen + now_s, so everything the instrument logged
        # since its start (frames, events, channels) falls after the old epoch.
        published = self.clock.at(wall_s)
        start = self._last_seen_s + now_s
        if published is not None and published > start:
            start = published
        self.t_offset_s = start - now_s
        log.warning(
            "instrument clock went back to %.3f s: it was restarted; epoch %d, "
            "times shifted by %.3f s, new registration reference",
            now_s,
            self.epoch,
            self.t_offset_s,
        )
        for fn in self._epoch_listeners:
            fn(self.epoch, self.t_offset_s)


async def every(
    period_s: float,
    body: Callable[[], Awaitable[None]],
    *,
    catch_up_s: float = 0.0,
    skipped: Callable[[int], None] | None = None,
) -> None:
    """Run ``body`` every ``period_s`` on an absolute schedule, for ever.

    A tick that comes late by up to ``catch_up_s`` is followed by the missed
    ones at once, so the average rate holds (the offset stream: the event
    loop's sleeps are rounded up to whole milliseconds, which alone would turn
    1 kHz into about 700 Hz). Later than that, the schedule restarts from now
    rather than bursting (polls after a reconnect), and ``skipped`` is told
    how many ticks were left out. A tick whose instrument call failed is
    skipped; the link reconnects.
    """
    loop = asyncio.get_running_loop()
    next_t = loop.time()
    while True:
        next_t += period_s
        delay = next_t - loop.time()
        await asyncio.sleep(delay if delay > 0 else 0.0)
        late = loop.time() - next_t
        if late > max(period_s, catch_up_s):
            if skipped is not None:
                skipped(int(late / period_s))
            next_t = loop.time()
        try:
            await body()
        except InstrumentDownError:
            continue

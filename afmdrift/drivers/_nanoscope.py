"""Async driver for a NanoScope/SCPI-style controller (the protocol of ``docs/protocol.md``).

:class:`NanoScopeDriver` implements :class:`afmdrift.drivers.Instrument` over
any :class:`~afmdrift.drivers._transport.Transport`. Each query and its reply
run as one blocking exchange in a worker thread, under one
:class:`asyncio.Lock` per connection, so concurrent tasks never interleave a
command with another's reply.

Robustness
----------
* Every command carries a fresh, increasing tag ``@N``. A complete late reply
  to an earlier query (lower tag, e.g. after a timeout) is skipped; a reply
  with an unknown tag or a header that does not answer the command is an
  :class:`OutOfSequenceError`.
* A garbled, partial, late or out-of-sequence reply raises a typed
  :class:`ProtocolError` (or :class:`InstrumentTimeout`) and the input is
  flushed until the line is quiet, so the next query starts clean. Frame
  blocks are CRC-checked (:class:`ChecksumError`): a wrong frame is never returned.
  These errors are not retried automatically; the caller decides.
* A lost connection (:class:`InstrumentDisconnected`) triggers a reconnect
  with bounded exponential backoff; an idempotent command is then sent once
  more, a non-idempotent one (``TIP:MAN``) raises after reconnecting.
* ``latest_frame()`` asks the cheap ``FRAME:INDEX?`` first and transfers the
  block only when the index changed.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from afmdrift.drivers._base import ConnectOnEnter
from afmdrift.drivers._protocol import (
    COMMANDS,
    InstrumentDisconnected,
    InstrumentTimeout,
    ProtocolError,
    Reply,
    check_header,
    check_tag,
    decode_channels,
    decode_event,
    decode_frame,
    decode_frame_header,
    encode_command,
    parse_command,
    parse_error_body,
    parse_floats,
    parse_int,
    parse_reply,
)
from afmdrift.drivers._transport import SerialTransport, Transport
from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo

__all__ = ["NanoScopeDriver"]

log = logging.getLogger(__name__)

T = TypeVar("T")


#: Event-log entries one ``events()`` call reads at most.
MAX_EVENTS_PER_READ = 4096
#: Longest flush of unread input before the line is reopened instead.
_FLUSH_MAX_S = 1.0


class NanoScopeDriver(ConnectOnEnter):
    """A NanoScope/SCPI-style controller seen through the :class:`Instrument` interface.

    Parameters
    ----------
    transport : Transport, str or callable
        An (unopened) transport, which the driver re-opens to reconnect; a URL
        for :class:`SerialTransport` (``/dev/ttyUSB0``, ``/dev/pts/N``,
        ``socket://127.0.0.1:5025``); or a factory called for a fresh
        transport on every (re)connect.
    timeout_s : float
        Longest wait for a reply line.
    frame_timeout_s : float
        Longest wait for a frame block's payload after its header.
    reconnect_attempts : int
        Attempts to (re)open the transport before :class:`InstrumentDisconnected`.
    backoff_initial_s, backoff_max_s : float
        Wait before attempt k is ``min(backoff_initial_s * 2**k, backoff_max_s)``.
    baudrate : int
        Used only when ``transport`` is a URL.
    event_budget_s : float
        Longest time one :meth:`events` call spends reading entry lines; a log
        that sends more than it can in this time is read on later calls.
    """

    def __init__(
        self,
        transport: Transport | str | Callable[[], Transport],
        *,
        timeout_s: float = 2.0,
        frame_timeout_s: float = 30.0,
        reconnect_attempts: int = 5,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 5.0,
        baudrate: int = 115200,
        event_budget_s: float = 0.25,
    ) -> None:
        self._factory: Callable[[], Transport] | None = None
        self._opened = False  # the current transport has been opened once
        self._unanswered_since: float | None = None  # see silent_s()
        if isinstance(transport, str):
            transport = SerialTransport(transport, baudrate=baudrate)
        elif not isinstance(transport, Transport):
            self._factory = transport
            transport = transport()
        for name, value in (
            ("timeout_s", timeout_s),
            ("frame_timeout_s", frame_timeout_s),
            ("backoff_initial_s", backoff_initial_s),
            ("backoff_max_s", backoff_max_s),
            ("event_budget_s", event_budget_s),
        ):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if reconnect_attempts < 1:
            raise ValueError(f"reconnect_attempts must be >= 1, got {reconnect_attempts}")
        self.transport = transport
        self.timeout_s = timeout_s
        self.frame_timeout_s = frame_timeout_s
        self.reconnect_attempts = reconnect_attempts
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.event_budget_s = event_budget_s
        self._lock = asyncio.Lock()
        self._io_lock = threading.Lock()  # a cancelled exchange may still run in its thread
        self._tags = itertools.count(1)
        self._dirty = False
        self._reopen = False  # the line carries more than a flush can clear
        self._cached: Frame | None = None
        self.info: InstrumentInfo | None = None  # from the last identify()
        #: Entries the last :meth:`events` call left unread although the log
        #: announced them (0 when it read the whole log).
        self.event_backlog = 0
        self._log_faults: set[str] = set()  # kinds of event-log fault reported
        self.frame_transfers = 0  # frame blocks received (for cache checks and stats)
        self.resyncs = 0  # times the input was flushed after a bad reply
        self.stale_replies = 0  # late replies to earlier queries, skipped

    # ---------------------------------------------------------------- lifecycle

    async def connect(self) -> None:
        """Open the transport, retrying with backoff."""
        async with self._lock:
            await self._open_with_backoff()

    async def close(self) -> None:
        """Close the transport (idempotent)."""
        async with self._lock:
            await asyncio.to_thread(self._close_sync)

    def _close_sync(self) -> None:
        with self._io_lock:
            self.transport.close()

    async def _open_with_backoff(self) -> None:
        last: InstrumentDisconnected | None = None
        for attempt in range(self.reconnect_attempts):
            if attempt:
                delay = min(self.backoff_initial_s * 2 ** (attempt - 1), self.backoff_max_s)
                log.info("%s: reconnect attempt %d in %.2f s", self.transport.name, attempt, delay)
                await asyncio.sleep(delay)
            try:
                await asyncio.to_thread(self._reopen_sync)
            except InstrumentDisconnected as err:
                last = err
                continue
            return
        raise InstrumentDisconnected(
            f"{self.transport.name}: could not connect after {self.reconnect_attempts} "
            f"attempt(s): {last}"
        )

    def _reopen_sync(self) -> None:
        with self._io_lock:
            self._reopen_locked()

    def _reopen_locked(self) -> None:
        self.transport.close()
        if self._factory is not None and self._opened:
            self.transport = self._factory()
        self.transport.open()
        self._opened = True
        self._dirty = False
        self._reopen = False

    # ---------------------------------------------------------------- exchange core

    def silent_s(self) -> float:
        """Seconds the driver has been waiting on the instrument without a byte
        arriving (0 while nothing is asked or replies flow).

        A call that is answered ends the wait; one that fails leaves it running
        until a later call is answered, so a dropped line shows up here within
        seconds, long before the driver's own retries give up.
        """
        since = self._unanswered_since
        if since is None:
            return 0.0
        return max(0.0, time.monotonic() - max(since, self.transport.last_rx_s))

    async def _call(self, fn: Callable[[], T], *, idempotent: bool = True) -> T:
        async with self._lock:
            if self._unanswered_since is None:
                self._unanswered_since = time.monotonic()
            result = await self._call_locked(fn, idempotent=idempotent)
            self._unanswered_since = None
            return result

    async def _call_locked(self, fn: Callable[[], T], *, idempotent: bool) -> T:
        """One exchange (the lock held), reconnecting once when the line is lost."""
        if not self.transport.is_open:
            await self._open_with_backoff()
        try:
            return await asyncio.to_thread(self._guarded, fn)
        except InstrumentDisconnected as err:
            log.warning("%s: connection lost (%s); reconnecting", self.transport.name, err)
            await self._open_with_backoff()
            if not idempotent:
                raise
        except asyncio.CancelledError:
            self._dirty = True
            raise
        return await asyncio.to_thread(self._guarded, fn)

    def _guarded(self, fn: Callable[[], T]) -> T:
        with self._io_lock:
            if self._reopen:
                log.info("%s: reopening the line to drop an unread reply", self.transport.name)
                self._reopen_locked()
            if self._dirty:
                self._resync()
            try:
                return fn()
            except (ProtocolError, InstrumentTimeout) as err:
                where = (
                    "" if str(err).startswith(self.transport.name) else f"{self.transport.name}: "
                )
                log.warning("%s%s; resynchronising", where, err)
                self._resync()
                raise

    def _resync(self) -> None:
        self.resyncs += 1
        self._dirty = False
        started = time.monotonic()
        self.transport.flush_input(max_s=_FLUSH_MAX_S)
        if time.monotonic() - started >= _FLUSH_MAX_S:
            # The line never went quiet (a reply without end): only a new
            # connection clears it.
            self._reopen = True

    def _send(self, header: str, *args: float | int | str, query: bool) -> tuple[int, str]:
        tag = next(self._tags) % 10**10
        data = encode_command(header, *args, query=query, tag=tag)
        self.transport.write(data)
        return tag, data.decode("ascii").strip()

    def _read_tagged(
        self, tag: int, *, fence: int | None = None, timeout_s: float | None = None
    ) -> Reply:
        """The next reply line carrying ``tag`` (or ``fence``, a later query sent
        behind it), skipping complete late replies to earlier queries (lower
        tags, including their frame payloads)."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise InstrumentTimeout(f"{self.transport.name}: timed out waiting for @{tag}")
            reply = parse_reply(self.transport.read_line(remaining))
            if reply.tag is None or reply.tag >= tag:
                if fence is not None and reply.tag == fence:
                    return reply
                check_tag(reply, tag)
                return reply
            self.stale_replies += 1
            log.info("%s: skipping a late reply tagged @%d", self.transport.name, reply.tag)
            if reply.header == "#FRAME":
                stale = decode_frame_header(reply)
                if stale is not None:
                    self.transport.read_exact(stale.nbytes, self.frame_timeout_s)

    def _read_reply(self, tag: int, header: str, command: str) -> Reply:
        reply = self._read_tagged(tag)
        check_header(reply, header, command=command)
        return reply

    def _query_sync(self, header: str, *args: float | int | str) -> str:
        tag, text = self._send(header, *args, query=True)
        return self._read_reply(tag, header, text).body

    def _set_sync(self, header: str, *args: float | int | str) -> None:
        tag, text = self._send(header, *args, query=False)
        self._read_reply(tag, "OK", text)

    async def _query(self, header: str, *args: float | int | str) -> str:
        return await self._call(lambda: self._query_sync(header, *args))

    async def _set(self, header: str, *args: float | int | str) -> None:
        idempotent = COMMANDS[header].idempotent
        await self._call(lambda: self._set_sync(header, *args), idempotent=idempotent)

    async def query(self, text: str) -> str:
        """Send one raw command (e.g. ``"SCAN:SIZE?"``) and return its reply body.

        For set commands the body is empty (the controller answered ``OK``).
        An ``ERR`` reply raises :class:`InstrumentError` with its code.
        """
        cmd = parse_command(text.encode("ascii", errors="replace"))

        def run() -> str:
            tag, sent = self._send(cmd.header, *cmd.args, query=cmd.query)
            expect = cmd.header if cmd.query else "OK"
            return self._read_reply(tag, expect, sent).body

        spec = COMMANDS.get(cmd.header)
        return await self._call(run, idempotent=spec is not None and spec.idempotent)

    # ---------------------------------------------------------------- Instrument

    async def identify(self) -> InstrumentInfo:
        """``*IDN?`` → vendor, model, serial, firmware."""
        body = await self._query("*IDN")
        parts = body.split(",")
        if len(parts) != 4:
            raise ProtocolError(f"*IDN reply needs 4 fields, got {body[:80]!r}")
        self.info = InstrumentInfo(*parts)
        return self.info

    async def now_s(self) -> float:
        """``SYST:TIME?``: the instrument clock in s."""
        return parse_floats(await self._query("SYST:TIME"), 1, "SYST:TIME")[0]

    async def frame_index(self) -> int:
        """Index of the last completed frame, -1 before the first."""
        return parse_int(await self._query("FRAME:INDEX"), "FRAME:INDEX")

    async def fetch_frame(self) -> Frame | None:
        """Transfer the last completed frame (always; see :meth:`latest_frame`)."""
        frame = await self._call(self._frame_sync)
        if frame is not None:
            self._cached = frame
        return frame

    def _frame_sync(self) -> Frame | None:
        tag, text = self._send("FRAME:DATA", query=True)
        reply = self._read_reply(tag, "#FRAME", text)
        header = decode_frame_header(reply)
        if header is None:
            return None
        payload = self.transport.read_exact(header.nbytes, self.frame_timeout_s)
        frame = decode_frame(header, payload)
        self.frame_transfers += 1
        return frame

    async def latest_frame(self) -> Frame | None:
        """The last completed frame; re-uses the cached one when its index is unchanged."""
        index = await self.frame_index()
        if index < 0:
            return None
        if self._cached is not None and self._cached.index == index:
            return self._cached
        return await self.fetch_frame()

    async def read_channels(self) -> ChannelSample:
        """``CHAN?``: temperature, humidity, ... at the instrument's current time."""
        return decode_channels(await self._query("CHAN"))

    async def event_count(self) -> int:
        """Number of entries in the event log."""
        return parse_int(await self._query("EVENT:COUNT"), "EVENT:COUNT")

    async def events(self, start: int = 0) -> list[Event]:
        """Entries ``start, start+1, ...`` of the event log, as many as one bounded
        read takes (at most ``MAX_EVENTS_PER_READ`` lines in ``event_budget_s``);
        :attr:`event_backlog` says how many more the log announced.

        A log that announces more entries than it sends, or streams without
        end, costs at most that budget: it is reported once (a warning naming
        the instrument) and read on from where this call stopped."""
        if start < 0:
            raise ValueError(f"events: start must be >= 0, got {start}")
        return await self._call(lambda: self._events_sync(start))

    def _events_sync(self, start: int) -> list[Event]:
        """One bounded read of the event log (see :meth:`events`).

        ``SYST:TIME?`` is sent right behind ``EVENT:LOG?`` as a fence: its
        reply follows the log's last line, so a log that announces more lines
        than it sends is over when the fence arrives, not after a timeout.
        """
        tag, text = self._send("EVENT:LOG", start, query=True)
        fence, _ = self._send("SYST:TIME", query=True)
        self._dirty = True  # until the fence's reply is read
        head = self._read_reply(tag, "EVENT:LOG", text)
        first, count = (parse_int(p, "EVENT:LOG") for p in _two(head.body, "EVENT:LOG"))
        if first != start or count < 0:
            raise ProtocolError(f"EVENT:LOG reply {head.body!r} does not answer start={start}")
        out: list[Event] = []
        deadline = time.monotonic() + self.event_budget_s
        fenced = False
        # At most MAX_EVENTS_PER_READ lines and event_budget_s per call: memory
        # and time stay bounded whatever the instrument announces or sends.
        while len(out) < min(count, MAX_EVENTS_PER_READ):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                reply = self._read_tagged(tag, fence=fence, timeout_s=remaining)
            except InstrumentTimeout:
                break
            if reply.tag == fence:
                fenced = True
                break
            check_header(reply, "EVENT", command=text)
            index, event = decode_event(reply.body)
            if index != start + len(out):
                raise ProtocolError(
                    f"event line {index} out of order (expected {start + len(out)})"
                )
            out.append(event)
        backlog = count - len(out)
        if fenced:
            self._dirty = False
            if backlog:
                self._report_log(
                    "short",
                    f"its event log announced {count} entries from {start} but sent "
                    f"{len(out)}; taking those",
                )
            backlog = 0
        elif backlog == 0:
            self._read_reply(fence, "SYST:TIME", "SYST:TIME?")
            self._dirty = False
        elif backlog > MAX_EVENTS_PER_READ or len(out) < MAX_EVENTS_PER_READ:
            # Lines still on their way (or without end): skipping them on the next
            # call would cost more than a new connection.
            self._reopen = True
            self._report_log(
                "flood",
                f"its event log announced {count} entries from {start}; read {len(out)} "
                f"within {self.event_budget_s:g} s, the rest on later polls",
            )
        self.event_backlog = backlog
        return out

    def _report_log(self, kind: str, text: str) -> None:
        """Warn once per kind of event-log fault, naming the instrument; later ones at debug."""
        level = logging.DEBUG if kind in self._log_faults else logging.WARNING
        self._log_faults.add(kind)
        who = self.transport.name
        if self.info is not None:
            i = self.info
            who = f"{i.vendor} {i.model} (serial {i.serial}) at {who}"
        log.log(level, "instrument %s: %s (reported once)", who, text)

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        """``SCAN:OFFS x,y``: command the absolute XY scan offset in nm."""
        await self._set("SCAN:OFFS", float(x_nm), float(y_nm))

    async def get_offset(self) -> tuple[float, float]:
        x, y = parse_floats(await self._query("SCAN:OFFS"), 2, "SCAN:OFFS")
        return x, y

    # ---------------------------------------------------------------- scan control

    async def configure_scan(
        self,
        *,
        size_nm: tuple[float, float] | None = None,
        pixels: tuple[int, int] | None = None,
        line_rate_hz: float | None = None,
    ) -> None:
        """Set scan size ``(x_nm, y_nm)``, pixels ``(cols, rows)`` and line rate.

        The controller refuses (``-221 Settings conflict``) while scanning and
        rejects out-of-range values with ``-222``; both raise :class:`InstrumentError`.
        """
        if size_nm is not None:
            await self._set("SCAN:SIZE", float(size_nm[0]), float(size_nm[1]))
        if pixels is not None:
            await self._set("SCAN:PIX", int(pixels[0]), int(pixels[1]))
        if line_rate_hz is not None:
            await self._set("SCAN:RATE", float(line_rate_hz))

    async def scan_size_nm(self) -> tuple[float, float]:
        x, y = parse_floats(await self._query("SCAN:SIZE"), 2, "SCAN:SIZE")
        return x, y

    async def pixels(self) -> tuple[int, int]:
        """``(cols, rows)``."""
        cols, rows = (
            parse_int(p, "SCAN:PIX") for p in _two(await self._query("SCAN:PIX"), "SCAN:PIX")
        )
        return cols, rows

    async def line_rate_hz(self) -> float:
        return parse_floats(await self._query("SCAN:RATE"), 1, "SCAN:RATE")[0]

    async def start_scan(self) -> None:
        await self._set("SCAN:START")

    async def stop_scan(self) -> None:
        await self._set("SCAN:STOP")

    async def scanning(self) -> bool:
        """``SCAN:STAT?`` is ``RUN``."""
        body = await self._query("SCAN:STAT")
        if body not in ("RUN", "IDLE"):
            raise ProtocolError(f"SCAN:STAT reply must be RUN or IDLE, got {body[:40]!r}")
        return body == "RUN"

    # ---------------------------------------------------------------- tip, errors

    async def tip_move(self, x_nm: float, y_nm: float) -> None:
        """Move the tip to ``(x_nm, y_nm)`` within the scan area."""
        await self._set("TIP:MOVE", float(x_nm), float(y_nm))

    async def manipulate(self, x0_nm: float, y0_nm: float, x1_nm: float, y1_nm: float) -> None:
        """Push with the tip from ``(x0, y0)`` to ``(x1, y1)`` nm (not retried on reconnect)."""
        await self._set("TIP:MAN", float(x0_nm), float(y0_nm), float(x1_nm), float(y1_nm))

    async def next_error(self) -> tuple[int, str]:
        """Pop the oldest entry of the controller's error queue; ``(0, "No error")`` if empty."""
        return parse_error_body(await self._query("SYST:ERR"))

    async def clear_errors(self) -> None:
        """``*CLS``: empty the error queue."""
        await self._set("*CLS")


def _two(body: str, what: str) -> tuple[str, str]:
    parts = body.split(",")
    if len(parts) != 2:
        raise ProtocolError(f"{what}: expected 2 values, got {body[:80]!r}")
    return parts[0], parts[1]

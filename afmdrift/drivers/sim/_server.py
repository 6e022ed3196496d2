"""The simulator's protocol server: the simulated AFM behind a real line.

:class:`SimulatorServer` speaks exactly the protocol of ``docs/protocol.md``
(the codec is :mod:`afmdrift.drivers._protocol`) on loopback TCP or on a
pseudo-terminal, so a client connects with the same serial code as to a real
controller (``socket://127.0.0.1:N`` or ``/dev/pts/N``).

Virtual clock
-------------
Simulated time runs ``speed`` times faster than wall time:
``t_virtual = t0 + speed · (t_wall − t_wall0)``. A periodic tick advances the
simulator to the current virtual time in worker threads, so frames complete
while nobody asks and a client sees a continuously running instrument; each
command first advances by at most one step (:attr:`SimulatorServer.step_s`).
When the physics cannot keep up with ``speed`` the instrument's clock
(``SYST:TIME?``) falls behind the nominal virtual clock rather than skipping.

Fault injection
---------------
:class:`ServerFaults` (``server.faults``) perturbs the next reply or replies, for
tests of clients: corrupt bytes, delay, drop, truncate, send a stale reply
first, or close the connection. Faults are queued and each applies to one
reply (optionally only to replies of one command header). A server can be
stopped and started again on the same TCP port.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import re
import tty
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from afmdrift.drivers._protocol import (
    COMMANDS,
    ERROR_MESSAGES,
    LINE_MAX,
    NO_ERROR,
    Command,
    CommandError,
    args_count_ok,
    encode_channels,
    encode_error,
    encode_event,
    encode_frame_reply,
    encode_no_frame,
    encode_ok,
    encode_value,
    parse_args_floats,
    parse_command,
)
from afmdrift.drivers.sim._clock import VirtualClock
from afmdrift.drivers.sim._running import RunningSimulation
from afmdrift.errors import AfmdriftError
from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo

__all__ = [
    "ERROR_QUEUE_SIZE",
    "ServerFaults",
    "SimulatedInstrument",
    "SimulatorServer",
    "VirtualClock",
]

log = logging.getLogger(__name__)

#: Entries kept in the error queue; an overflow replaces the newest with -350.
ERROR_QUEUE_SIZE = 16
_TAG_RE = re.compile(rb"@([0-9]{1,10}) ")


class SimulatedInstrument(Protocol):
    """What the server needs from the simulator (:class:`afmdrift.drivers.sim.SimulatedAFM`)."""

    @property
    def now_s(self) -> float: ...
    def advance_to(self, t_s: float, *, render_all: bool = True) -> object: ...
    def identify(self) -> InstrumentInfo: ...
    @property
    def scan_size_nm(self) -> tuple[float, float]: ...
    @property
    def pixels(self) -> tuple[int, int]: ...
    @property
    def line_rate_hz(self) -> float: ...
    def configure_scan(
        self,
        *,
        size_nm: tuple[float, float] | None = None,
        pixels: tuple[int, int] | None = None,
        line_rate_hz: float | None = None,
    ) -> None: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    @property
    def running(self) -> bool: ...
    def latest_frame(self) -> Frame | None: ...
    def read_channels(self) -> ChannelSample: ...
    @property
    def events(self) -> list[Event]: ...
    def set_offset(self, x_nm: float, y_nm: float) -> None: ...
    def get_offset(self) -> tuple[float, float]: ...
    def tip_move(self, x_nm: float, y_nm: float) -> None: ...
    def manipulate(self, x0_nm: float, y0_nm: float, x1_nm: float, y1_nm: float) -> object: ...


# --------------------------------------------------------------------------- faults

FaultKind = Literal[
    "corrupt", "delay", "drop", "truncate", "stale", "disconnect", "overcount", "flood"
]


@dataclass(slots=True)
class _Fault:
    kind: FaultKind
    match: str | None
    remaining: int
    delay_s: float = 0.0
    nbytes: int = 1
    keep_bytes: int = 0
    where: Literal["any", "header", "payload"] = "any"
    #: ``overcount``: entries announced beyond those sent; ``flood``: the count claimed.
    claim: int = 0


class ServerFaults:
    """Queued perturbations of the server's next replies (for client tests).

    Each method queues a fault that applies to the next ``count`` replies
    whose command header equals ``match`` (any reply when ``match`` is
    ``None``; headers are canonical, e.g. ``"FRAME:DATA"``, ``"SYST:TIME"``).
    Faults apply in the order queued, one fault per reply. ``applied`` lists
    ``(kind, header)`` for every fault applied, so a test can check it fired.

    Parameters
    ----------
    seed : int
        Seeds the choice of corrupted bytes.
    """

    def __init__(self, *, seed: int = 0, random_rate: float = 0.0) -> None:
        if not 0.0 <= random_rate <= 1.0:
            raise ValueError(f"random_rate must be in [0, 1], got {random_rate}")
        self._queue: deque[_Fault] = deque()
        self._rng = np.random.default_rng(seed)
        self.applied: list[tuple[str, str]] = []
        #: Probability that a reply with no queued fault gets a random one
        #: (corrupted byte, truncation, drop, 0.3 s delay, stale reply or, on
        #: TCP, a disconnect): the faulty line of a soak test.
        self.random_rate = random_rate

    def corrupt_next_reply(
        self,
        *,
        count: int = 1,
        nbytes: int = 1,
        where: Literal["any", "header", "payload"] = "any",
        match: str | None = None,
    ) -> None:
        """Flip bits in ``nbytes`` random bytes of the reply (never creating or removing a
        line terminator in text). ``where="payload"`` corrupts only a frame block's payload,
        ``"header"`` only the first line."""
        self._push(_Fault("corrupt", match, count, nbytes=nbytes, where=where))

    def delay_next_reply(self, delay_s: float, *, count: int = 1, match: str | None = None) -> None:
        """Send the reply ``delay_s`` wall seconds late."""
        self._push(_Fault("delay", match, count, delay_s=delay_s))

    def drop_next_reply(self, *, count: int = 1, match: str | None = None) -> None:
        """Never send the reply (the client times out)."""
        self._push(_Fault("drop", match, count))

    def truncate_next_reply(
        self, keep_bytes: int, *, count: int = 1, match: str | None = None
    ) -> None:
        """Send only the first ``keep_bytes`` bytes of the reply (a partial reply)."""
        self._push(_Fault("truncate", match, count, keep_bytes=keep_bytes))

    def stale_next_reply(self, *, count: int = 1, match: str | None = None) -> None:
        """Send the previous reply of this connection again before the real one
        (an out-of-sequence reply)."""
        self._push(_Fault("stale", match, count))

    def disconnect_on_next_reply(self, *, match: str | None = None) -> None:
        """Close the connection instead of replying (on a pty: drop the reply)."""
        self._push(_Fault("disconnect", match, 1))

    def overcount_event_log(self, extra: int, *, count: int = 1) -> None:
        """Make the next ``EVENT:LOG?`` replies announce ``extra`` more entries
        than they send (a lying event log: the client waits for lines that never come)."""
        if extra < 1:
            raise ValueError(f"extra must be >= 1, got {extra}")
        self._push(_Fault("overcount", "EVENT:LOG", count, claim=extra))

    def flood_event_log(self, *, claim: int = 10**9, count: int = 1) -> None:
        """Make the next ``EVENT:LOG?`` replies announce ``claim`` entries and stream
        event lines without end, until the client closes the connection (an event
        log gone mad). The connection answers nothing else meanwhile."""
        if claim < 1:
            raise ValueError(f"claim must be >= 1, got {claim}")
        self._push(_Fault("flood", "EVENT:LOG", count, claim=claim))

    def clear(self) -> None:
        """Forget every queued fault."""
        self._queue.clear()

    @property
    def pending(self) -> int:
        """Replies still to be perturbed."""
        return sum(f.remaining for f in self._queue)

    def _push(self, fault: _Fault) -> None:
        if fault.remaining < 1:
            raise ValueError(f"count must be >= 1, got {fault.remaining}")
        if fault.delay_s < 0 or fault.nbytes < 1 or fault.keep_bytes < 0:
            raise ValueError(f"invalid fault parameters: {fault}")
        self._queue.append(fault)

    def take(self, header: str) -> _Fault | None:
        """The fault for a reply to ``header`` (consumed), or ``None``."""
        for fault in self._queue:
            if fault.match is None or fault.match == header:
                fault.remaining -= 1
                if fault.remaining == 0:
                    self._queue.remove(fault)
                self.applied.append((fault.kind, header))
                return fault
        if self.random_rate and self._rng.random() < self.random_rate:
            fault = self._random_fault()
            self.applied.append((fault.kind, header))
            return fault
        return None

    def _random_fault(self) -> _Fault:
        kinds: tuple[FaultKind, ...] = (
            "corrupt",
            "truncate",
            "drop",
            "delay",
            "stale",
            "disconnect",
        )
        kind = kinds[int(self._rng.integers(len(kinds)))]
        return _Fault(kind, None, 1, delay_s=0.3, keep_bytes=int(self._rng.integers(0, 12)))

    def corrupt(self, data: bytes, fault: _Fault) -> bytes:
        out = bytearray(data)
        first_nl = data.find(b"\n")
        lo, hi = 0, len(data)
        if fault.where == "header":
            hi = max(first_nl, 1)
        elif fault.where == "payload" and 0 <= first_nl < len(data) - 1:
            lo = first_nl + 1
        text_end = first_nl if first_nl >= 0 else len(data)
        for _ in range(fault.nbytes):
            pos = int(self._rng.integers(lo, hi))
            if pos <= text_end and out[pos] == 0x0A:
                pos = max(lo, pos - 1)
            flipped = out[pos] ^ int(self._rng.integers(1, 256))
            if pos <= text_end and flipped == 0x0A:
                flipped ^= 0x01
            out[pos] = flipped
        return bytes(out)


# --------------------------------------------------------------------------- lines


class _Line(Protocol):
    async def read(self) -> bytes: ...
    async def write(self, data: bytes) -> None: ...
    async def close(self) -> None: ...


class _StreamLine:
    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._reader = reader
        self._writer = writer

    async def read(self) -> bytes:
        return await self._reader.read(1 << 16)

    async def write(self, data: bytes) -> None:
        self._writer.write(data)
        await self._writer.drain()

    async def close(self) -> None:
        self._writer.close()
        with contextlib.suppress(ConnectionError):
            await self._writer.wait_closed()


class _FdLine:
    """The master side of a pseudo-terminal, non-blocking, driven by the event loop."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        os.set_blocking(fd, False)

    async def _wait(self, add: Callable[..., None], remove: Callable[[int], bool]) -> None:
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def ready() -> None:
            if not fut.done():
                fut.set_result(None)

        add(self._fd, ready)
        try:
            await fut
        finally:
            remove(self._fd)

    async def read(self) -> bytes:
        loop = asyncio.get_running_loop()
        while True:
            try:
                return os.read(self._fd, 1 << 16)
            except BlockingIOError:
                await self._wait(loop.add_reader, loop.remove_reader)
            except OSError as err:
                if err.errno == errno.EIO:  # no slave open; we keep one, so this is shutdown
                    return b""
                raise

    async def write(self, data: bytes) -> None:
        loop = asyncio.get_running_loop()
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                await self._wait(loop.add_writer, loop.remove_writer)
                continue
            view = view[n:]

    async def close(self) -> None:
        return None


class _DisconnectRequestedError(Exception):
    """Internal: a fault asked to drop the connection."""


# --------------------------------------------------------------------------- server


class SimulatorServer:
    """Serve a simulated instrument over loopback TCP or a pseudo-terminal.

    Parameters
    ----------
    sim : SimulatedInstrument
        The simulated AFM (:class:`afmdrift.drivers.sim.SimulatedAFM`).
    speed : float
        Virtual seconds per wall second.
    faults : ServerFaults, optional
        Fault injection (default: a new, empty one; see ``server.faults``).
    tick_s : float
        Wall seconds between background advances of the simulation.
    clock : VirtualClock, optional
        Overrides ``speed`` (for tests with a controlled wall clock).

    Use as ``async with SimulatorServer(sim) as srv: port = await srv.start_tcp(0)``.
    Several clients may connect one after the other or at once; they share the
    instrument. :meth:`stop` closes the listener, every connection and the pty.
    """

    def __init__(
        self,
        sim: SimulatedInstrument,
        *,
        speed: float = 1.0,
        faults: ServerFaults | None = None,
        tick_s: float = 0.05,
        clock: VirtualClock | None = None,
    ) -> None:
        self.sim = sim
        self.running = RunningSimulation(
            sim,
            clock=clock if clock is not None else VirtualClock(speed=speed, start_s=sim.now_s),
            tick_s=tick_s,
        )
        self.clock = self.running.clock
        self.faults = faults if faults is not None else ServerFaults()
        self.tick_s = tick_s
        self.port: int | None = None
        self.pty_path: str | None = None
        self.connections = 0  # connections accepted so far (TCP)
        self._errors: deque[tuple[int, str]] = deque()
        self._sim_lock = self.running.lock
        self._frame_cache: tuple[int, bytes] | None = None
        self._tcp: asyncio.Server | None = None
        self._pty_fds: tuple[int, int] | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._handlers: dict[tuple[str, bool], Callable[[Command], bytes]] = {
            ("*IDN", True): self._idn,
            ("*CLS", False): self._cls,
            ("SYST:ERR", True): self._syst_err,
            ("SYST:TIME", True): lambda c: encode_value("SYST:TIME", self.sim.now_s, tag=c.tag),
            ("SCAN:SIZE", True): lambda c: encode_value(
                "SCAN:SIZE", *self.sim.scan_size_nm, tag=c.tag
            ),
            ("SCAN:SIZE", False): self._set_size,
            ("SCAN:PIX", True): lambda c: encode_value("SCAN:PIX", *self.sim.pixels, tag=c.tag),
            ("SCAN:PIX", False): self._set_pixels,
            ("SCAN:RATE", True): lambda c: encode_value(
                "SCAN:RATE", self.sim.line_rate_hz, tag=c.tag
            ),
            ("SCAN:RATE", False): self._set_rate,
            ("SCAN:START", False): self._start,
            ("SCAN:STOP", False): self._stop,
            ("SCAN:STAT", True): lambda c: encode_value(
                "SCAN:STAT", "RUN" if self.sim.running else "IDLE", tag=c.tag
            ),
            ("SCAN:OFFS", True): lambda c: encode_value(
                "SCAN:OFFS", *self.sim.get_offset(), tag=c.tag
            ),
            ("SCAN:OFFS", False): self._set_offset,
            ("FRAME:INDEX", True): self._frame_index,
            ("FRAME:TIME", True): self._frame_time,
            ("FRAME:DATA", True): self._frame_data,
            ("CHAN", True): lambda c: encode_channels(self.sim.read_channels(), tag=c.tag),
            ("TIP:MOVE", False): self._tip_move,
            ("TIP:MAN", False): self._tip_man,
            ("EVENT:COUNT", True): lambda c: encode_value(
                "EVENT:COUNT", len(self.sim.events), tag=c.tag
            ),
            ("EVENT:LOG", True): self._event_log,
        }

    # ---------------------------------------------------------------- lifecycle

    async def __aenter__(self) -> SimulatorServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def _ensure_ticker(self) -> None:
        self.running.start()

    def advance(self) -> None:
        """Run the simulation up to the virtual clock's now (thread-safe; see
        :meth:`RunningSimulation.advance`)."""
        self.running.advance()

    @property
    def step_s(self) -> float:
        """Largest virtual time one physics step covers: a quarter of a tick."""
        return self.running.step_s

    async def start_tcp(self, port: int = 0, *, host: str = "127.0.0.1") -> int:
        """Listen on ``host:port`` (0 picks a free port); returns the bound port.

        After :meth:`stop`, ``start_tcp(server.port)`` listens on the same port again.
        """
        if self._tcp is not None:
            raise RuntimeError(f"already listening on {host}:{self.port}")
        self._tcp = await asyncio.start_server(self._on_tcp, host, port, reuse_address=True)
        self.port = int(self._tcp.sockets[0].getsockname()[1])
        self._ensure_ticker()
        log.info("simulator serving on %s:%d", host, self.port)
        return self.port

    async def start_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns the slave path (``/dev/pts/N``)."""
        if self._pty_fds is not None:
            raise RuntimeError(f"already serving on {self.pty_path}")
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing, 8-bit clean
        self._pty_fds = (master, slave)  # keeping the slave open survives client closes
        self.pty_path = os.ttyname(slave)
        self._spawn(self._serve_line(_FdLine(master), "pty"))
        self._ensure_ticker()
        log.info("simulator serving on %s", self.pty_path)
        return self.pty_path

    async def stop(self) -> None:
        """Close the listener, every connection, the pty and the ticker (idempotent)."""
        ticker = self.running.take_ticker()
        listener, self._tcp = self._tcp, None
        if listener is not None:
            listener.close()  # stop accepting; connections are cancelled below
        tasks = list(self._tasks)
        if ticker is not None:
            tasks.append(ticker)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if listener is not None:
            await listener.wait_closed()
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                os.close(fd)
            self._pty_fds = None
            self.pty_path = None

    def _spawn(self, coro: Coroutine[object, object, None]) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        peer = writer.get_extra_info("peername")
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        log.info("client %s connected", peer)
        await self._serve_line(_StreamLine(reader, writer), f"tcp {peer}")

    async def _serve_line(self, line: _Line, name: str) -> None:
        buf = bytearray()
        skipping = False  # inside an over-long line
        last_reply = b""
        try:
            while True:
                chunk = await line.read()
                if not chunk:
                    break
                buf += chunk
                while (end := buf.find(b"\n")) >= 0:
                    raw = bytes(buf[: end + 1])
                    del buf[: end + 1]
                    if skipping:
                        skipping = False
                        with self._sim_lock:
                            reply = self._push_error(
                                -363, f"line longer than {LINE_MAX} bytes", None
                            )
                        header = "ERR"
                    else:
                        reply, header = await asyncio.to_thread(self.handle_line, raw)
                    await self._send(line, reply, header, last_reply, name)
                    last_reply = reply
                if len(buf) > LINE_MAX:
                    buf.clear()
                    skipping = True
        except _DisconnectRequestedError:
            log.info("%s: closing the connection (injected fault)", name)
        except ConnectionError as err:
            log.info("%s: connection lost: %s", name, err)
        finally:
            await line.close()
            log.info("%s: client gone", name)

    async def _send(
        self, line: _Line, reply: bytes, header: str, last_reply: bytes, name: str
    ) -> None:
        fault = self.faults.take(header)
        if fault is None:
            await line.write(reply)
            return
        log.info("%s: injecting %s fault into the reply to %s", name, fault.kind, header)
        if fault.kind == "delay":
            await asyncio.sleep(fault.delay_s)
            await line.write(reply)
        elif fault.kind == "truncate":
            await line.write(reply[: fault.keep_bytes])
        elif fault.kind == "corrupt":
            await line.write(self.faults.corrupt(reply, fault))
        elif fault.kind == "stale":
            await line.write(last_reply + reply)
        elif fault.kind == "disconnect" and isinstance(line, _StreamLine):
            raise _DisconnectRequestedError
        elif fault.kind == "overcount":
            await line.write(_announce(reply, lambda start, n: n + fault.claim))
        elif fault.kind == "flood":
            await self._flood(line, reply, fault.claim)
        # "drop" (and "disconnect" on a pty): send nothing

    async def _flood(self, line: _Line, reply: bytes, claim: int) -> None:
        """Announce ``claim`` entries, then send made-up ``note`` entries until the
        client hangs up (or ``claim`` lines went out)."""
        head = reply.split(b"\n", 1)[0] + b"\n"
        m = _TAG_RE.match(head)
        tag = int(m.group(1)) if m else None
        start = int(head.rsplit(b" ", 1)[-1].split(b",")[0])
        await line.write(_announce(head, lambda s, n: claim))
        t_s = self.clock.now_s()
        sent = 0
        while sent < claim:
            chunk = min(256, claim - sent)
            await line.write(
                b"".join(
                    encode_event(start + sent + k, Event(t_s, "note", 0.0, 0.0), tag=tag)
                    for k in range(chunk)
                )
            )
            sent += chunk

    # ---------------------------------------------------------------- dispatch

    def handle_line(self, line: bytes) -> tuple[bytes, str]:
        """Answer one command line; returns the reply bytes and the command header.

        Never raises: every problem becomes an ``ERR`` reply and an entry in the
        error queue, as on a real controller. Thread-safe: the server calls it
        from worker threads so that physics never blocks the event loop.
        """
        with self._sim_lock:
            return self._handle_locked(line)

    def _handle_locked(self, line: bytes) -> tuple[bytes, str]:
        m = _TAG_RE.match(line)
        tag = int(m.group(1)) if m else None
        try:
            cmd = parse_command(line)
        except CommandError as err:
            return self._push_error(err.code, str(err), tag), "ERR"
        spec = COMMANDS.get(cmd.header)
        handler = self._handlers.get((cmd.header, cmd.query))
        if spec is None or handler is None:
            return self._push_error(-113, cmd.header, tag), cmd.header
        bad = args_count_ok(spec, cmd)
        if bad is not None:
            return self._push_error(bad[0], bad[1], tag), cmd.header
        try:
            # One bounded step keeps the answer fresh at low speed without making a
            # query wait for a long render at high speed (the ticker does the rest).
            self.running.advance_step_locked(self.clock.now_s())
            return handler(cmd), cmd.header
        except CommandError as err:
            return self._push_error(err.code, str(err), tag), cmd.header
        except (AfmdriftError, ValueError) as err:
            return self._push_error(-222, f"{cmd.text}: {err}", tag), cmd.header
        except Exception as err:
            log.exception("simulator failed on %r", cmd.text)
            return self._push_error(
                -200, f"{cmd.text}: {type(err).__name__}: {err}", tag
            ), cmd.header

    def _push_error(self, code: int, detail: str, tag: int | None) -> bytes:
        """Queue and encode error ``code`` as SCPI does: ``"<standard message>;<detail>"``."""
        text = ERROR_MESSAGES.get(code, "Error") + (f";{detail}" if detail else "")
        if len(self._errors) >= ERROR_QUEUE_SIZE:
            self._errors[-1] = (-350, ERROR_MESSAGES[-350])
        else:
            self._errors.append((code, text))
        return encode_error(code, text, tag=tag)

    @property
    def error_queue(self) -> list[tuple[int, str]]:
        """Entries not yet read by ``SYST:ERR?`` (oldest first)."""
        return list(self._errors)

    # ---------------------------------------------------------------- handlers

    def _idn(self, c: Command) -> bytes:
        info = self.sim.identify()
        fields = [
            re.sub(r"[^ -~]|,", "_", str(v)) or "-"
            for v in (info.vendor, info.model, info.serial, info.firmware)
        ]
        return b"%s*IDN %s\n" % (_tag_bytes(c.tag), ",".join(fields).encode("ascii"))

    def _cls(self, c: Command) -> bytes:
        self._errors.clear()
        return encode_ok(tag=c.tag)

    def _syst_err(self, c: Command) -> bytes:
        code, msg = self._errors.popleft() if self._errors else NO_ERROR
        text = msg.replace('"', "'")
        return b'%sSYST:ERR %d,"%s"\n' % (_tag_bytes(c.tag), code, text.encode("ascii", "replace"))

    def _require_stopped(self, c: Command) -> None:
        if self.sim.running:
            raise CommandError(-221, f"{c.text}: stop scanning first (SCAN:STOP)")

    def _set_size(self, c: Command) -> bytes:
        self._require_stopped(c)
        x, y = parse_args_floats(c)
        self.sim.configure_scan(size_nm=(x, y))
        return encode_ok(tag=c.tag)

    def _set_pixels(self, c: Command) -> bytes:
        self._require_stopped(c)
        if not all(re.fullmatch(r"[0-9]{1,6}", a) for a in c.args):
            raise CommandError(-104, f"{c.text}: pixels must be positive integers")
        self.sim.configure_scan(pixels=(int(c.args[0]), int(c.args[1])))
        return encode_ok(tag=c.tag)

    def _set_rate(self, c: Command) -> bytes:
        self._require_stopped(c)
        (rate,) = parse_args_floats(c)
        self.sim.configure_scan(line_rate_hz=rate)
        return encode_ok(tag=c.tag)

    def _start(self, c: Command) -> bytes:
        if not self.sim.running:
            self.sim.start()
        return encode_ok(tag=c.tag)

    def _stop(self, c: Command) -> bytes:
        if self.sim.running:
            self.sim.stop()
        return encode_ok(tag=c.tag)

    def _set_offset(self, c: Command) -> bytes:
        x, y = parse_args_floats(c)
        self.sim.set_offset(x, y)
        return encode_ok(tag=c.tag)

    def _tip_move(self, c: Command) -> bytes:
        x, y = parse_args_floats(c)
        self.sim.tip_move(x, y)
        return encode_ok(tag=c.tag)

    def _tip_man(self, c: Command) -> bytes:
        x0, y0, x1, y1 = parse_args_floats(c)
        self.sim.manipulate(x0, y0, x1, y1)
        return encode_ok(tag=c.tag)

    def _frame_index(self, c: Command) -> bytes:
        frame = self.sim.latest_frame()
        return encode_value("FRAME:INDEX", -1 if frame is None else frame.index, tag=c.tag)

    def _frame_time(self, c: Command) -> bytes:
        frame = self.sim.latest_frame()
        if frame is None:
            raise CommandError(-230, "no frame completed yet")
        return encode_value(
            "FRAME:TIME",
            frame.index,
            frame.t_start_s,
            frame.t_end_s,
            frame.direction.value,
            tag=c.tag,
        )

    def _frame_data(self, c: Command) -> bytes:
        frame = self.sim.latest_frame()
        if frame is None:
            return encode_no_frame(tag=c.tag)
        if self._frame_cache is None or self._frame_cache[0] != frame.index:
            self._frame_cache = (frame.index, encode_frame_reply(frame))
        return _tag_bytes(c.tag) + self._frame_cache[1]

    def _event_log(self, c: Command) -> bytes:
        if not re.fullmatch(r"[0-9]{1,9}", c.args[0]):
            raise CommandError(-104, f"{c.text}: start must be a non-negative integer")
        start = int(c.args[0])
        events = self.sim.events[start:]
        out = [encode_value("EVENT:LOG", start, len(events), tag=c.tag)]
        out.extend(encode_event(start + k, e, tag=c.tag) for k, e in enumerate(events))
        return b"".join(out)


def _announce(reply: bytes, count: Callable[[int, int], int]) -> bytes:
    """``reply`` (an ``EVENT:LOG start,n`` reply) with its header announcing
    ``count(start, n)`` entries instead of ``n``; the entry lines are unchanged."""
    head, sep, rest = reply.partition(b"\n")
    prefix, _, values = head.rpartition(b" ")
    start, n = (int(v) for v in values.split(b","))
    return b"%s %d,%d%s%s" % (prefix, start, count(start, n), sep, rest)


def _tag_bytes(tag: int | None) -> bytes:
    return b"" if tag is None else b"@%d " % tag

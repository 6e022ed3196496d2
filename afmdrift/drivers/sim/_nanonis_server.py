"""The simulated AFM behind the Nanonis TCP protocol.

:class:`NanonisSimServer` serves the same :class:`SimulatedAFM` physics on the
same :class:`VirtualClock` as :class:`SimulatorServer`, but speaks the Nanonis
TCP protocol (codec: :mod:`afmdrift.drivers.nanonis._codec`) with the
controller's semantics, for the commands afmdrift uses
(:data:`~afmdrift.drivers.nanonis._codec.COMMANDS`):

* SI units on the wire (m, m/s, s); the simulator works in nm.
* The scan frame is a centre and a size: the centre is the simulator's
  commanded offset (the window's first pixel) plus half the size.
  ``Scan.FrameSet`` moves it (an ``offset_move`` in the simulator, with its
  creep and hysteresis) and may resize the frame; rotation is not simulated
  (a non-zero angle is refused).
* The scan runs line after line (``Scan.SpeedGet``: forward time per line is
  the trace, backward the retrace); ``Scan.WaitEndOfScan`` returns at the next
  end of a frame after the request arrives, or after its timeout (wall ms).
  ``Scan.FrameDataGrab`` returns the last completed frame of the ``Z (m)``
  channel; the backward direction returns the same (trace) image.
* ``Piezo.DriftCompSet``/``Get``: the piezo moves the scan window at the set
  velocity until the displacement reaches the saturation limit (% of the
  piezo range, the scenario's ``[controller]``) on an axis, which then
  reports saturated; switching it off releases the displacement, or keeps it
  on a controller that does (see :meth:`SimulatedAFM.set_drift_compensation`).
* ``Signals.NamesGet``/``ValsGet``: :data:`SIGNAL_NAMES`, among them the head
  temperature, the humidity and ``Clock (s)``, the instrument's (virtual) time,
  which Nanonis does not otherwise report.

Every reply ends with the error block; a command that fails is answered with
a non-zero status and a description, a command the server does not know with
the error block alone. A request body larger than ``max_body_bytes`` closes the
connection (nothing after it can be framed).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from afmdrift.drivers._protocol import ProtocolError
from afmdrift.drivers.nanonis._codec import (
    COMMANDS,
    HEADER_SIZE,
    decode_body,
    decode_header,
    encode_reply,
)
from afmdrift.drivers.sim._clock import VirtualClock
from afmdrift.drivers.sim._instrument import SimulatedAFM
from afmdrift.drivers.sim._running import RunningSimulation
from afmdrift.errors import AfmdriftError

__all__ = ["CLOCK_SIGNAL", "SCAN_CHANNEL", "SIGNAL_NAMES", "NanonisSimServer"]

log = logging.getLogger(__name__)

_NM = 1e-9  # m per nm

#: The simulated controller's signals (index = position), as ``Signals.NamesGet`` lists them.
SIGNAL_NAMES: tuple[str, ...] = (
    "Current (A)",
    "Bias (V)",
    "X (m)",
    "Y (m)",
    "Temperature (C)",
    "Humidity (%)",
    "Clock (s)",
    *(f"Input {k} (V)" for k in range(7, 14)),
    "Z (m)",
)
#: Index of the height channel, the only one the scan buffer records.
SCAN_CHANNEL = SIGNAL_NAMES.index("Z (m)")
#: The signal that reports the instrument's time in s.
CLOCK_SIGNAL = "Clock (s)"

#: Largest request body accepted (the largest request, Signals.ValsGet of all signals, is tiny).
MAX_REQUEST_BYTES = 1 << 20


class _CommandFailedError(Exception):
    """Internal: answer the command with this error description."""


class NanonisSimServer:
    """Serve a :class:`SimulatedAFM` over the Nanonis TCP protocol on loopback.

    Parameters
    ----------
    sim : SimulatedAFM
    speed : float
        Virtual seconds per wall second.
    tick_s : float
        Wall seconds between background advances (also how often a waiting
        ``Scan.WaitEndOfScan`` looks for the end of a frame).
    clock : VirtualClock, optional
        Overrides ``speed``.

    Use as ``async with NanonisSimServer(sim) as srv: port = await srv.start_tcp(0)``.
    """

    def __init__(
        self,
        sim: SimulatedAFM,
        *,
        speed: float = 1.0,
        tick_s: float = 0.01,
        clock: VirtualClock | None = None,
        max_body_bytes: int = MAX_REQUEST_BYTES,
    ) -> None:
        self.sim = sim
        self.running = RunningSimulation(
            sim,
            clock=clock if clock is not None else VirtualClock(speed=speed, start_s=sim.now_s),
            tick_s=tick_s,
        )
        self.clock = self.running.clock
        self.max_body_bytes = max_body_bytes
        self.port: int | None = None
        self.connections = 0
        self.requests: dict[str, int] = {}  # command name -> requests answered
        self._tcp: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._frame_cache: tuple[int, int, bytes] | None = None
        # A handler returns the reply's values, or the complete reply (cached frames).
        self._handlers: dict[str, Callable[[tuple[Any, ...]], tuple[Any, ...] | bytes]] = {
            "Scan.Action": self._action,
            "Scan.StatusGet": lambda a: (int(self.sim.running),),
            "Scan.FrameSet": self._frame_set,
            "Scan.FrameGet": self._frame_get,
            "Scan.BufferGet": self._buffer_get,
            "Scan.SpeedGet": self._speed_get,
            "Scan.FrameDataGrab": self._frame_data_grab,
            "FolMe.XYPosGet": self._folme_get,
            "FolMe.XYPosSet": self._folme_set,
            "Piezo.RangeGet": lambda a: tuple(r * _NM for r in self.sim.piezo_range_nm),
            "Piezo.DriftCompSet": self._drift_comp_set,
            "Piezo.DriftCompGet": self._drift_comp_get,
            "Signals.NamesGet": lambda a: (list(SIGNAL_NAMES),),
            "Signals.ValsGet": self._vals_get,
        }

    # ---------------------------------------------------------------- lifecycle

    async def __aenter__(self) -> NanonisSimServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start_tcp(self, port: int = 0, *, host: str = "127.0.0.1") -> int:
        """Listen on ``host:port`` (0 picks a free port); returns the bound port."""
        if self._tcp is not None:
            raise RuntimeError(f"already listening on {host}:{self.port}")
        self._tcp = await asyncio.start_server(self._on_tcp, host, port, reuse_address=True)
        self.port = int(self._tcp.sockets[0].getsockname()[1])
        self.running.start()
        log.info("Nanonis simulator serving on %s:%d", host, self.port)
        return self.port

    async def stop(self) -> None:
        """Close the listener, every connection and the ticker (idempotent)."""
        ticker = self.running.take_ticker()
        listener, self._tcp = self._tcp, None
        if listener is not None:
            listener.close()
        tasks = list(self._tasks)
        if ticker is not None:
            tasks.append(ticker)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if listener is not None:
            await listener.wait_closed()

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        peer = writer.get_extra_info("peername")
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        log.info("Nanonis client %s connected", peer)
        try:
            while True:
                head = await reader.readexactly(HEADER_SIZE)
                header = decode_header(head, max_body_bytes=self.max_body_bytes)
                body = await reader.readexactly(header.body_size)
                if header.name == "Scan.WaitEndOfScan":
                    reply = await self._wait_end_of_scan(body)
                else:
                    reply = await asyncio.to_thread(self.handle, header.name, body)
                if header.response:
                    writer.write(reply)
                    await writer.drain()
        except asyncio.IncompleteReadError:
            pass
        except ProtocolError as err:
            log.warning("Nanonis client %s: %s; closing the connection", peer, err)
        except ConnectionError as err:
            log.info("Nanonis client %s: connection lost: %s", peer, err)
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
            log.info("Nanonis client %s gone", peer)

    # ---------------------------------------------------------------- dispatch

    def handle(self, name: str, body: bytes) -> bytes:
        """Answer one request (thread-safe); returns the complete reply."""
        spec = COMMANDS.get(name)
        handler = self._handlers.get(name)
        if spec is None or handler is None:
            return encode_reply(name, error=(1, f"Unknown command {name}"), types=())
        try:
            args, end = decode_body(spec.args, body, what=f"request {name}")
            if end != len(body):
                raise ProtocolError(
                    f"request {name}: {len(body) - end} byte(s) after the arguments"
                )
        except ProtocolError as err:
            return encode_reply(name, error=(1, str(err)), types=())
        with self.running.lock:
            self.running.advance_step_locked(self.clock.now_s())
            try:
                values = handler(args)
            except (_CommandFailedError, AfmdriftError, ValueError) as err:
                return encode_reply(name, error=(1, str(err)), types=())
            self.requests[name] = self.requests.get(name, 0) + 1
            return values if isinstance(values, bytes) else encode_reply(name, *values)

    async def _wait_end_of_scan(self, body: bytes) -> bytes:
        name = "Scan.WaitEndOfScan"
        try:
            (timeout_ms,), _ = decode_body(COMMANDS[name].args, body, what=f"request {name}")
        except ProtocolError as err:
            return encode_reply(name, error=(1, str(err)), types=())
        start = self._latest_index()
        deadline = math.inf if timeout_ms < 0 else time.monotonic() + timeout_ms / 1000.0
        while True:
            await asyncio.to_thread(self.running.advance)
            if self._latest_index() != start:
                self.requests[name] = self.requests.get(name, 0) + 1
                return encode_reply(name, 0, "")
            if time.monotonic() >= deadline:
                return encode_reply(name, 1, "")
            await asyncio.sleep(min(self.running.tick_s, max(deadline - time.monotonic(), 0.0)))

    def _latest_index(self) -> int:
        with self.running.lock:
            frame = self.sim.latest_frame()
        return -1 if frame is None else frame.index

    # ---------------------------------------------------------------- scan

    def _action(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        action, _direction = args
        if action == 0:
            self.sim.start()
        elif action == 1:
            self.sim.stop()
        else:
            raise _CommandFailedError(f"scan action {action} is not simulated (0 start, 1 stop)")
        return ()

    def _origin_nm(self) -> tuple[float, float]:
        return self.sim.get_offset()

    def _frame_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        ox, oy = self._origin_nm()
        w, h = self.sim.scan_size_nm
        return ((ox + w / 2) * _NM, (oy + h / 2) * _NM, w * _NM, h * _NM, 0.0)

    def _frame_set(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        cx, cy, w_m, h_m, angle = (float(a) for a in args)
        if angle != 0.0:
            raise _CommandFailedError(f"frame angle {angle} deg: rotation is not simulated")
        w, h = w_m / _NM, h_m / _NM
        old_w, old_h = self.sim.scan_size_nm
        # The client sends float32: a size within its precision is unchanged.
        if abs(w - old_w) > 1e-6 * old_w or abs(h - old_h) > 1e-6 * old_h:
            self.sim.configure_scan(size_nm=(w, h))
        else:
            w, h = old_w, old_h
        x, y = cx / _NM - w / 2, cy / _NM - h / 2
        ox, oy = self._origin_nm()
        if abs(x - ox) > 1e-6 or abs(y - oy) > 1e-6:
            self.sim.set_offset(x, y)
        return ()

    def _buffer_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        cols, rows = self.sim.pixels
        return (np.array([SCAN_CHANNEL]), cols, rows)

    def _speed_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        g = self.sim.geometry
        fwd = g.trace_fraction * g.line_period_s
        bwd = g.line_period_s - fwd
        width_m = g.size_nm[0] * _NM
        return (width_m / fwd, width_m / bwd if bwd > 0 else 0.0, fwd, bwd, 1, fwd / bwd)

    def _frame_data_grab(self, args: tuple[Any, ...]) -> bytes:
        name = "Scan.FrameDataGrab"
        channel, direction = args
        if channel != SCAN_CHANNEL:
            raise _CommandFailedError(
                f"channel {channel} is not acquired (the scan buffer records {SCAN_CHANNEL})"
            )
        if direction not in (0, 1):
            raise _CommandFailedError(f"data direction {direction}: 1 forward, 0 backward")
        frame = self.sim.latest_frame()
        if frame is None:
            raise _CommandFailedError("no scan frame has been completed yet")
        key = (frame.index, int(direction))
        if self._frame_cache is None or self._frame_cache[:2] != key:
            data = np.asarray(frame.heights_nm, dtype=np.float64) * _NM
            up = 1 if frame.direction.value == "up" else 0
            self._frame_cache = (*key, encode_reply(name, SIGNAL_NAMES[SCAN_CHANNEL], data, up))
        return self._frame_cache[2]

    # ---------------------------------------------------------------- follow me

    def _folme_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        ox, oy = self._origin_nm()
        tx, ty = self.sim.tip_position_nm
        return ((ox + tx) * _NM, (oy + ty) * _NM)

    def _folme_set(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        x, y, _wait = args
        ox, oy = self._origin_nm()
        self.sim.tip_move(x / _NM - ox, y / _NM - oy)
        return ()

    # ---------------------------------------------------------------- piezo

    def _drift_comp_set(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        on_off, vx, vy, vz, limit = args
        if on_off not in (0, 1, 2):
            raise _CommandFailedError(f"compensation on/off {on_off}: 0 no change, 1 on, 2 off")
        on = None if on_off == 0 else on_off == 1
        self.sim.set_drift_compensation(
            on=on, velocity_nm_per_s=(vx / _NM, vy / _NM, vz / _NM), limit_pct=float(limit)
        )
        return ()

    def _drift_comp_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        on, (vx, vy, vz), (sx, sy, sz), limit = self.sim.drift_compensation()
        return (int(on), vx * _NM, vy * _NM, vz * _NM, int(sx), int(sy), int(sz), limit)

    # ---------------------------------------------------------------- signals

    def _vals_get(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        indexes, _wait = args
        n = len(SIGNAL_NAMES)
        bad = [int(i) for i in indexes if not 0 <= i < n]
        if bad:
            raise _CommandFailedError(f"signal index {bad[0]} is out of range (0..{n - 1})")
        channels = self.sim.read_channels().values
        ox, oy = self._origin_nm()
        tx, ty = self.sim.tip_position_nm
        table = {
            "Current (A)": 1e-10,
            "Bias (V)": 0.5,
            "X (m)": (ox + tx) * _NM,
            "Y (m)": (oy + ty) * _NM,
            "Temperature (C)": channels.get("temperature_c", math.nan),
            "Humidity (%)": channels.get("humidity_pct", math.nan),
            CLOCK_SIGNAL: self.sim.now_s,
        }
        return (np.array([table.get(SIGNAL_NAMES[int(i)], 0.0) for i in indexes]),)

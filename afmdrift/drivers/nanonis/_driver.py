"""Async client for a Nanonis (SPECS) controller over its TCP interface.

:class:`NanonisDriver` implements :class:`afmdrift.drivers.Instrument` and
:class:`afmdrift.drivers.VelocityActuator` with the codec of
:mod:`afmdrift.drivers.nanonis._codec`, over any
:class:`~afmdrift.drivers.Transport` (``nanonis://HOST:PORT`` opens a
:class:`~afmdrift.drivers.SerialTransport` on ``socket://HOST:PORT``). One
request and its reply run as one blocking exchange in a worker thread under
one :class:`asyncio.Lock`, as in the NanoScope driver.

What the controller does not have, the driver keeps itself:

Time
    Nanonis has no clock query. ``now_s()`` is the host's monotonic clock
    since the driver was made, or, with ``clock_signal``, the value of that
    signal (the simulator offers ``"Clock (s)"``, which runs on its virtual
    time).
Frames
    ``latest_frame()`` asks ``Scan.WaitEndOfScan`` with a short timeout
    (``wait_ms``). When a scan ended, the frame is read at once with
    ``Scan.FrameDataGrab``; its geometry comes from ``Scan.FrameGet`` and
    ``Scan.BufferGet``, its timing from ``Scan.SpeedGet`` (line time is
    forward + backward time per line) and the time the end was seen. The
    controller reports the next end of scan after the request, so a scan
    that ends between two waits is missed. With ``wait_transport`` (a second
    port of the TCP interface) the waits run on their own connection without
    a timeout, and the next one is sent the moment a reply arrives, a frame
    before the next end: no end of scan is missed. On the shared connection,
    polling continuously (``frame_poll_interval_s`` <= ``wait_ms``) keeps
    the window to the duration of the other commands.
Event log
    Nanonis logs nothing afmdrift can read, so the driver logs what moves the
    image: every offset it commands (``offset_move`` with the delta), and the
    displacement the controller's drift compensation (``Piezo.DriftComp``)
    applied since the last entry, booked at every ``events()`` call and
    before every change of velocity. ``get_offset()`` is the scan frame centre
    (or the follow-me position) plus that displacement, so
    ``p = m + O(t) − O(t_ref)`` holds whatever moved the piezo.

Units: Nanonis speaks SI (m, m/s, s); the driver converts to nm and nm/s.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal
from urllib.parse import urlsplit

import numpy as np

from afmdrift.drivers._base import ConnectOnEnter, Recentre
from afmdrift.drivers._protocol import InstrumentDisconnected, InstrumentTimeout, ProtocolError
from afmdrift.drivers._transport import SerialTransport, Transport
from afmdrift.drivers.nanonis._codec import (
    HEADER_SIZE,
    MAX_BODY_BYTES,
    decode_header,
    decode_reply,
    encode_request,
)
from afmdrift.records import (
    ChannelSample,
    Event,
    EventKind,
    Frame,
    InstrumentInfo,
    ScanDirection,
)

__all__ = [
    "NANONIS_SCHEME",
    "DriftCompState",
    "NanonisDriver",
    "nanonis_socket_url",
]

log = logging.getLogger(__name__)

#: URL scheme that selects this driver.
NANONIS_SCHEME = "nanonis://"

_M_TO_NM = 1e9

OffsetMode = Literal["frame", "follow_me"]


def nanonis_socket_url(url: str) -> str:
    """``nanonis://HOST:PORT`` → ``socket://HOST:PORT``.

    Raises
    ------
    ValueError
        Not a ``nanonis://HOST:PORT`` URL with a port in 1..65535.
    """
    if not url.startswith(NANONIS_SCHEME):
        raise ValueError(f"not a nanonis:// URL: {url!r}")
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None or not 0 < port < 65536 or parts.path not in ("", "/"):
        raise ValueError(f"expected nanonis://HOST:PORT with a port in 1..65535, got {url!r}")
    return f"socket://{parts.hostname}:{port}"


def _as_transport(transport: Transport | str) -> Transport:
    if isinstance(transport, str):
        url = nanonis_socket_url(transport) if transport.startswith(NANONIS_SCHEME) else transport
        return SerialTransport(url)
    return transport


@dataclass(frozen=True, slots=True)
class DriftCompState:
    """The controller's drift compensation (``Piezo.DriftCompGet``), in nm and nm/s."""

    on: bool
    velocity_nm_per_s: tuple[float, float, float]
    saturated: tuple[bool, bool, bool]
    limit_pct: float


#: Largest ramp of the compensation between two logged ``offset_move``
#: entries, nm (:meth:`NanonisDriver._book_comp`), and the shortest step.
COMP_LOG_NM = 1.0
_MIN_COMP_LOG_S = 1e-3

#: Shortest time over which a displacement handed to the frame centre is
#: ramped out (one interval between velocity commands), instrument s.
_MIN_UNWIND_S = 0.05


class NanonisDriver(ConnectOnEnter):
    """A Nanonis controller seen through the :class:`Instrument` interface.

    Parameters
    ----------
    transport : Transport or str
        An unopened transport (re-opened to reconnect), or a URL:
        ``nanonis://HOST:PORT`` or ``socket://HOST:PORT``.
    wait_transport : Transport or str, optional
        A second connection (same forms) used only for ``Scan.WaitEndOfScan``,
        with a wait always outstanding on it. None: waits share ``transport``.
    channel_index : int
        Scan channel that ``Scan.FrameDataGrab`` reads (an index of the
        channels ``Scan.BufferGet`` lists; a height channel in metres).
    direction : {"forward", "backward"}
        Which trace of each line to read.
    channels : mapping of str to str
        afmdrift channel name (``temperature_c``) → Nanonis signal name
        (``"Temperature (C)"``) read with ``Signals.ValsGet``.
    offset_mode : {"frame", "follow_me"}
        ``set_offset`` moves the scan frame centre (``Scan.FrameSet``) or the
        tip (``FolMe.XYPosSet``).
    clock_signal : str
        Signal giving the instrument time in s; empty: the host clock.
    wait_ms : int
        Timeout of each ``Scan.WaitEndOfScan``.
    drift_comp_limit_pct : float
        Saturation limit sent with ``Piezo.DriftCompSet`` (% of the piezo range).
    recentre_fraction : float
        Re-centre the drift compensation once its displacement reaches this
        fraction of the limit on an axis (or the controller reports saturation).
    release : {"unknown", "reset", "keep"}
        What switching the compensation off does to its displacement on this
        controller. Only with ``"reset"`` does a re-centre switch it off and
        on (the displacement released at once); the frame after it, and a
        saturation the books cannot explain, check that, and a controller
        found to keep it is taken as ``"keep"`` from then on. Otherwise a
        re-centre does not switch: the frame centre takes the displacement
        over and the compensation ramps it out over the next interval
        between velocity commands, right whatever off does (the image stands
        off by up to the displacement for that interval).
    min_recentre_interval_s : float
        Instrument seconds at least between two re-centres; and while the
        behaviour is being learned, none until the last one was checked.
        A compensation that needs more is held at its limit and counted
        (:attr:`recentres_held`): never a storm of moves.
    comp_log_step_s : float
        Instrument seconds of compensation ramp per logged ``offset_move``.
    timeout_s : float
        Longest wait for a reply (beyond ``wait_ms`` for ``Scan.WaitEndOfScan``).
    reconnect_attempts : int
        Attempts to (re)open the transport.
    max_body_bytes : int
        Largest reply body accepted.
    """

    def __init__(
        self,
        transport: Transport | str,
        *,
        wait_transport: Transport | str | None = None,
        channel_index: int = 0,
        direction: Literal["forward", "backward"] = "forward",
        channels: Mapping[str, str] | None = None,
        offset_mode: OffsetMode = "frame",
        clock_signal: str = "",
        wait_ms: int = 200,
        drift_comp_limit_pct: float = 10.0,
        recentre_fraction: float = 0.8,
        release: Literal["unknown", "reset", "keep"] = "unknown",
        min_recentre_interval_s: float = 60.0,
        comp_log_step_s: float = 5.0,
        timeout_s: float = 5.0,
        reconnect_attempts: int = 3,
        max_body_bytes: int = MAX_BODY_BYTES,
    ) -> None:
        transport = _as_transport(transport)
        if direction not in ("forward", "backward"):
            raise ValueError(f"direction must be 'forward' or 'backward', got {direction!r}")
        if offset_mode not in ("frame", "follow_me"):
            raise ValueError(f"offset_mode must be 'frame' or 'follow_me', got {offset_mode!r}")
        if not 0 < drift_comp_limit_pct <= 100:
            raise ValueError(
                f"drift_comp_limit_pct must be in (0, 100], got {drift_comp_limit_pct}"
            )
        if not 0 < recentre_fraction <= 1:
            raise ValueError(f"recentre_fraction must be in (0, 1], got {recentre_fraction}")
        if release not in ("unknown", "reset", "keep"):
            raise ValueError(f"release must be 'unknown', 'reset' or 'keep', got {release!r}")
        if not 0 <= min_recentre_interval_s <= 86400:
            raise ValueError(
                f"min_recentre_interval_s must be in [0, 86400], got {min_recentre_interval_s}"
            )
        if not comp_log_step_s > 0:
            raise ValueError(f"comp_log_step_s must be > 0, got {comp_log_step_s}")
        if wait_ms < 0 or timeout_s <= 0 or reconnect_attempts < 1:
            raise ValueError(
                f"need wait_ms >= 0, timeout_s > 0, reconnect_attempts >= 1; got {wait_ms}, "
                f"{timeout_s}, {reconnect_attempts}"
            )
        self.transport = transport
        self.wait_transport = None if wait_transport is None else _as_transport(wait_transport)
        self.channel_index = int(channel_index)
        self.direction = direction
        self.channel_map = dict(channels or {})
        self.offset_mode: OffsetMode = offset_mode
        self.clock_signal = clock_signal
        self.wait_ms = int(wait_ms)
        self.drift_comp_limit_pct = float(drift_comp_limit_pct)
        self.recentre_fraction = float(recentre_fraction)
        #: What off does to the displacement, as configured or found.
        self.release: Literal["unknown", "reset", "keep"] = release
        self.min_recentre_interval_s = float(min_recentre_interval_s)
        self.comp_log_step_s = float(comp_log_step_s)
        self.timeout_s = float(timeout_s)
        self.reconnect_attempts = int(reconnect_attempts)
        self.max_body_bytes = int(max_body_bytes)
        self._lock = asyncio.Lock()
        self._io_lock = threading.Lock()
        self._wait_lock = asyncio.Lock()
        self._wait_io = threading.Lock()
        self._wait_pending = False  # a Scan.WaitEndOfScan request awaits its reply
        self._t0 = time.monotonic()
        self._signal_index: dict[str, int] = {}
        self._range_nm = (math.inf, math.inf)
        self._events: list[Event] = [Event(0.0, EventKind.POWER_ON)]
        self._latest: Frame | None = None
        self._next_index = 0
        # Drift compensation as the driver books it: velocity (nm/s) since
        # ``_comp_t``, displacement (nm) the controller applied since it was
        # switched on, and the part of it already logged as offset_move.
        self._comp_on = False
        self._comp_v = (0.0, 0.0)
        self._comp_t = 0.0
        self._comp_q = [0.0, 0.0]
        self._comp_saturated = [False, False]
        self.recentres = 0
        #: Re-centres the bound held back (the compensation stayed at its limit).
        self.recentres_held = 0
        #: Re-centres made, oldest first.
        self.recentre_log: list[Recentre] = []
        self._unchecked: Recentre | None = None
        self._unwind = (0.0, 0.0)  # displacement to ramp out with the next velocity
        self._last_set_t = math.inf  # instrument time of the last set_drift_velocity
        #: False after the daemon found the actuator doing what it cannot
        #: explain: no more re-centres.
        self.recentre_allowed = True
        self.frame_transfers = 0

    # ---------------------------------------------------------------- lifecycle

    async def connect(self) -> None:
        """Open the transport; read the signal names, piezo range and drift compensation."""
        async with self._lock:
            await self._open_with_retries()
        if self.wait_transport is not None:
            async with self._wait_lock:
                await self._open_with_retries(self.wait_transport)
        names = (await self.call("Signals.NamesGet"))[0]
        self._signal_index = {str(n): k for k, n in enumerate(names)}
        for key, signal in [*self.channel_map.items(), ("clock", self.clock_signal)]:
            if signal and signal not in self._signal_index:
                raise ProtocolError(
                    f"{self.transport.name}: signal {signal!r} (for {key}) is not among the "
                    f"controller's {len(names)} signals"
                )
        rx, ry, _ = await self.call("Piezo.RangeGet")
        self._range_nm = (float(rx) * _M_TO_NM, float(ry) * _M_TO_NM)
        state = await self.drift_comp()
        t = await self.now_s()
        # Compensation that was already running is booked from now on (its
        # earlier displacement is part of where the piezo stands).
        self._comp_on = state.on
        self._comp_v = state.velocity_nm_per_s[:2]
        self._comp_t = t
        self._comp_saturated = list(state.saturated[:2])

    async def _open_with_retries(self, transport: Transport | None = None) -> None:
        """(Re)open the command connection, or ``transport`` (the wait connection)."""
        transport = self.transport if transport is None else transport
        last: Exception | None = None
        for attempt in range(self.reconnect_attempts):
            if attempt:
                await asyncio.sleep(min(0.1 * 2**attempt, 2.0))
            try:
                await asyncio.to_thread(self._reopen_sync, transport)
                return
            except InstrumentDisconnected as err:
                last = err
        raise InstrumentDisconnected(
            f"{transport.name}: could not connect after {self.reconnect_attempts} "
            f"attempt(s): {last}"
        )

    def _reopen_sync(self, transport: Transport) -> None:
        with self._wait_io if transport is self.wait_transport else self._io_lock:
            transport.close()
            if transport is self.wait_transport:
                self._wait_pending = False
            transport.open()

    async def close(self) -> None:
        """Close the connections (idempotent)."""
        async with self._lock:
            await asyncio.to_thread(self._close_sync)
        if self.wait_transport is not None:
            # The wait in flight, if any, ends within ``wait_ms``; closing
            # waits for it rather than cutting a reply in half.
            async with self._wait_lock:
                await asyncio.to_thread(self._close_wait_sync)

    def _close_sync(self) -> None:
        with self._io_lock:
            self.transport.close()

    def _close_wait_sync(self) -> None:
        assert self.wait_transport is not None
        with self._wait_io:
            self.wait_transport.close()
            self._wait_pending = False

    # ---------------------------------------------------------------- exchange

    async def call(self, name: str, *args: Any, wait_s: float = 0.0) -> tuple[Any, ...]:
        """Send command ``name`` with ``args``; return its reply values.

        ``wait_s`` extends the reply timeout (for commands that block on the
        controller, like ``Scan.WaitEndOfScan``).

        Raises
        ------
        NanonisError
            The controller reported an error.
        ProtocolError, InstrumentTimeout, InstrumentDisconnected
            The reply was malformed, late, or the line was lost (the input is
            flushed after the first two, so the next command starts clean).
        """
        request = encode_request(name, *args)
        async with self._lock:
            if not self.transport.is_open:
                await self._open_with_retries()
            return await asyncio.to_thread(self._exchange, name, request, wait_s)

    def _exchange(self, name: str, request: bytes, wait_s: float) -> tuple[Any, ...]:
        with self._io_lock:
            try:
                self.transport.write(request)
                timeout = self.timeout_s + wait_s
                header = decode_header(
                    self.transport.read_exact(HEADER_SIZE, timeout),
                    max_body_bytes=self.max_body_bytes,
                )
                body = self.transport.read_exact(header.body_size, timeout)
                return decode_reply(name, header, body)
            except (ProtocolError, InstrumentTimeout) as err:
                log.warning("%s: %s: %s; resynchronising", self.transport.name, name, err)
                self.transport.flush_input()
                raise

    def _wait_exchange(self) -> bool:
        """Has the scan ended? (False: yes, True: not within ``wait_ms``.)

        The wait connection always has one ``Scan.WaitEndOfScan`` without a
        timeout outstanding: the controller reports the next end of scan
        after a request, so the next request goes out the moment a reply
        arrives, a whole frame before the next end. No end can fall between
        two waits. A reply not there within ``wait_ms`` leaves the request
        outstanding (and any part of the reply already read buffered).
        """
        transport = self.wait_transport
        assert transport is not None
        name = "Scan.WaitEndOfScan"
        request = encode_request(name, -1)
        with self._wait_io:
            try:
                if not self._wait_pending:
                    transport.write(request)
                    self._wait_pending = True
                try:
                    head = transport.read_exact(HEADER_SIZE, self.wait_ms / 1000.0)
                except InstrumentTimeout:
                    return True
                header = decode_header(head, max_body_bytes=self.max_body_bytes)
                body = transport.read_exact(header.body_size, self.timeout_s)
                self._wait_pending = False
                decode_reply(name, header, body)
                transport.write(request)
                self._wait_pending = True
                return False
            except (ProtocolError, InstrumentTimeout) as err:
                # A half-read reply cannot be resynchronised against a wait
                # that may answer later: start the connection afresh.
                log.warning("%s: %s: %s; reconnecting", transport.name, name, err)
                transport.close()
                self._wait_pending = False
                raise
            except BaseException:
                if not transport.is_open:
                    self._wait_pending = False
                raise

    # ---------------------------------------------------------------- Instrument

    async def identify(self) -> InstrumentInfo:
        """Vendor and model; the serial is the connection (Nanonis does not report one)."""
        await self.call("Scan.StatusGet")
        return InstrumentInfo("SPECS", "Nanonis", self.transport.name, "TCP interface")

    async def now_s(self) -> float:
        """Instrument time in s: the clock signal, or the host clock since the driver was made."""
        if not self.clock_signal:
            return time.monotonic() - self._t0
        (values,) = await self.call(
            "Signals.ValsGet", np.array([self._signal_index[self.clock_signal]]), 0
        )
        return float(values[0])

    async def read_channels(self) -> ChannelSample:
        """The mapped signals (``Signals.ValsGet``) at the instrument's current time."""
        keys = list(self.channel_map)
        indexes = [self._signal_index[self.channel_map[k]] for k in keys]
        if self.clock_signal:
            indexes.append(self._signal_index[self.clock_signal])
        if not indexes:
            return ChannelSample(t_s=await self.now_s())
        (values,) = await self.call("Signals.ValsGet", np.array(indexes), 0)
        if len(values) != len(indexes):
            raise ProtocolError(f"Signals.ValsGet: asked {len(indexes)} values, got {len(values)}")
        t = float(values[-1]) if self.clock_signal else time.monotonic() - self._t0
        return ChannelSample(
            t_s=t, values={k: float(v) for k, v in zip(keys, values, strict=False)}
        )

    async def latest_frame(self) -> Frame | None:
        """Wait up to ``wait_ms`` for an end of scan; read the new frame, else the last one."""
        if self.wait_transport is None:
            timed_out, _path = await self.call(
                "Scan.WaitEndOfScan", self.wait_ms, wait_s=self.wait_ms / 1000.0
            )
        else:
            async with self._wait_lock:
                if not self.wait_transport.is_open:
                    await self._open_with_retries(self.wait_transport)
                timed_out = await asyncio.to_thread(self._wait_exchange)
        if timed_out:
            return self._latest
        t_end = await self.now_s()
        frame = await self._grab(t_end)
        self._latest = frame
        return frame

    async def _grab(self, t_end_s: float) -> Frame:
        name, data, up = await self.call(
            "Scan.FrameDataGrab", self.channel_index, 1 if self.direction == "forward" else 0
        )
        _cx, _cy, width_m, height_m, _angle = await self.call("Scan.FrameGet")
        _chans, pixels, lines = await self.call("Scan.BufferGet")
        _vf, _vb, fwd_s, bwd_s, _keep, _ratio = await self.call("Scan.SpeedGet")
        rows, cols = data.shape
        if (rows, cols) != (lines, pixels) or rows < 2 or cols < 2:
            raise ProtocolError(
                f"Scan.FrameDataGrab gave {rows} × {cols} data, Scan.BufferGet says "
                f"{lines} lines × {pixels} pixels"
            )
        scale = _M_TO_NM if str(name).endswith("(m)") else 1.0
        heights = data.astype(np.float32) * np.float32(scale)
        line_s = float(fwd_s) + float(bwd_s)
        index = self._next_index
        self._next_index += 1
        self.frame_transfers += 1
        return Frame(
            index=index,
            heights_nm=heights,
            pixel_size_nm=(float(width_m) * _M_TO_NM / cols, float(height_m) * _M_TO_NM / rows),
            t_start_s=t_end_s - rows * line_s,
            t_end_s=t_end_s,
            direction=ScanDirection.UP if up else ScanDirection.DOWN,
        )

    async def events(self, start: int = 0) -> list[Event]:
        """The driver's log from ``start``, after booking the drift compensation up to now."""
        if start < 0:
            raise ValueError(f"events: start must be >= 0, got {start}")
        if self._comp_on:
            self._book_comp(await self.now_s())
        return self._events[start:]

    async def get_offset(self) -> tuple[float, float]:
        """Frame centre (or follow-me position) plus the compensation booked so far, nm."""
        x, y = await self._base_offset_nm()
        if self._comp_on:
            self._book_comp(await self.now_s())
        return x + self._comp_q[0], y + self._comp_q[1]

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        """Move the effective offset (see :meth:`get_offset`) to ``(x_nm, y_nm)``.

        The frame centre (or tip) moves by the difference; logged as ``offset_move``.
        """
        ex, ey = await self.get_offset()
        dx, dy = float(x_nm) - ex, float(y_nm) - ey
        await self._move_base(dx, dy)

    async def _base_offset_nm(self) -> tuple[float, float]:
        if self.offset_mode == "frame":
            cx, cy, *_ = await self.call("Scan.FrameGet")
        else:
            cx, cy = await self.call("FolMe.XYPosGet", 0)
        return float(cx) * _M_TO_NM, float(cy) * _M_TO_NM

    async def _move_base(self, dx_nm: float, dy_nm: float) -> None:
        if self.offset_mode == "frame":
            cx, cy, w, h, angle = await self.call("Scan.FrameGet")
            nx = float(cx) + dx_nm / _M_TO_NM
            ny = float(cy) + dy_nm / _M_TO_NM
            await self.call("Scan.FrameSet", nx, ny, w, h, angle)
            # The controller holds the centre as float32: log the move it made.
            done_x = (float(np.float32(nx)) - float(cx)) * _M_TO_NM
            done_y = (float(np.float32(ny)) - float(cy)) * _M_TO_NM
        else:
            x, y = await self.call("FolMe.XYPosGet", 0)
            await self.call("FolMe.XYPosSet", x + dx_nm / _M_TO_NM, y + dy_nm / _M_TO_NM, 0)
            done_x, done_y = dx_nm, dy_nm
        self._events.append(Event(await self.now_s(), EventKind.OFFSET_MOVE, done_x, done_y))

    # ---------------------------------------------------------------- drift compensation

    async def drift_comp(self) -> DriftCompState:
        """``Piezo.DriftCompGet`` in nm/s."""
        on, vx, vy, vz, sx, sy, sz, limit = await self.call("Piezo.DriftCompGet")
        return DriftCompState(
            on=bool(on),
            velocity_nm_per_s=(vx * _M_TO_NM, vy * _M_TO_NM, vz * _M_TO_NM),
            saturated=(bool(sx), bool(sy), bool(sz)),
            limit_pct=float(limit),
        )

    def _book_comp(self, t_s: float) -> None:
        """Log the displacement the compensation applied since the last booking.

        One ``offset_move`` per ``comp_log_step_s`` of instrument time (at the
        end of each step), or per :data:`COMP_LOG_NM` of ramp where that is
        sooner (a take-over ramped out in one interval), so the offset the
        service reconstructs from the log follows the ramp to within
        ``min(v · comp_log_step_s, COMP_LOG_NM)``.
        """
        t0 = self._comp_t
        if t_s <= t0:
            return
        speed = math.hypot(*self._comp_v)
        step_s = self.comp_log_step_s
        if speed > 0:
            step_s = min(step_s, max(COMP_LOG_NM / speed, _MIN_COMP_LOG_S))
        steps = max(1, math.ceil((t_s - t0) / step_s))
        for k in range(1, steps + 1):
            t = t_s if k == steps else t0 + k * step_s
            dt = t - self._comp_t
            self._comp_t = t
            step = [0.0, 0.0]
            for axis in range(2):
                if self._comp_saturated[axis]:
                    continue
                limit = self.drift_comp_limit_pct / 100.0 * self._range_nm[axis]
                q = min(max(self._comp_q[axis] + self._comp_v[axis] * dt, -limit), limit)
                step[axis] = q - self._comp_q[axis]
                self._comp_q[axis] = q
            if step[0] or step[1]:
                self._events.append(Event(t, EventKind.OFFSET_MOVE, step[0], step[1]))

    async def set_drift_velocity(self, vx_nm_per_s: float, vy_nm_per_s: float) -> None:
        """Move the image at this velocity with the controller's drift compensation.

        Books the displacement so far, reads the saturation back, re-centres
        when an axis saturated or came within ``recentre_fraction`` of the
        limit (the frame centre takes over the displacement and the
        compensation is released), then sets the new velocity (Vz = 0).
        """
        for name, v in (("vx_nm_per_s", vx_nm_per_s), ("vy_nm_per_s", vy_nm_per_s)):
            if not math.isfinite(v):
                raise ValueError(f"set_drift_velocity: {name} = {v} is not finite")
        state = await self.drift_comp()
        before = await self.now_s()
        if self._comp_on:
            self._book_comp(before)
        limits = [self.drift_comp_limit_pct / 100.0 * r for r in self._range_nm]
        near = any(
            abs(q) >= self.recentre_fraction * lim
            for q, lim in zip(self._comp_q, limits, strict=True)
        )
        if (
            self._unchecked is not None
            and self._unchecked.procedure == "release"
            and self._kept_by_saturation(state, limits)
        ):
            self.recentre_checked(kept=True)
        if self._comp_on and (any(state.saturated[:2]) or near):
            if self._may_recentre(before):
                await self._recentre()
                before = await self.now_s()
            else:
                self.recentres_held += 1
        # A displacement the frame centre took over but the compensation
        # still applies (a controller that keeps it) is ramped out over one
        # interval between calls, on top of the velocity asked.
        tick = before - self._last_set_t if before > self._last_set_t else 1.0
        tick = max(tick, _MIN_UNWIND_S)
        ux, uy = self._unwind
        self._unwind = (0.0, 0.0)
        vx = float(np.float32((vx_nm_per_s - ux / tick) / _M_TO_NM))
        vy = float(np.float32((vy_nm_per_s - uy / tick) / _M_TO_NM))
        await self._switch_velocity(1, (vx * _M_TO_NM, vy * _M_TO_NM), before)
        self._last_set_t = before
        self._comp_saturated = [False, False]

    async def _switch_velocity(
        self, action: int, v_nm_per_s: tuple[float, float], before: float | None = None
    ) -> None:
        """``Piezo.DriftCompSet`` (1: on at this velocity, 2: off), booked at the switch.

        The controller does not say when the command took effect; it did
        between the clock readings on either side of it. The old velocity is
        booked up to their midpoint and the new one from it, so a round trip
        of the line costs at most half a round trip × the velocity change
        (at 50× simulator speed a whole unbooked round trip per 0.1 s tick
        left a few % of the ramp out of the drift positions).
        """
        v_si = [v / _M_TO_NM for v in v_nm_per_s]
        if before is None:  # the clock just read by the caller, if any
            before = await self.now_s()
        await self.call("Piezo.DriftCompSet", action, *v_si, 0.0, self.drift_comp_limit_pct)
        t_switch = 0.5 * (before + await self.now_s())
        if self._comp_on:
            self._book_comp(t_switch)
        self._comp_t = max(self._comp_t, t_switch)
        self._comp_on = action == 1
        self._comp_v = v_nm_per_s if action == 1 else (0.0, 0.0)

    @property
    def unchecked_recentre(self) -> Recentre | None:
        """The last re-centre while its frame has not confirmed it."""
        return self._unchecked

    def _may_recentre(self, t_s: float) -> bool:
        """The bound: one re-centre per ``min_recentre_interval_s``, and none
        before the last one was checked on its frame."""
        if self._unchecked is not None or not self.recentre_allowed:
            return False
        last = self.recentre_log[-1].t_s if self.recentre_log else -math.inf
        return t_s - last >= self.min_recentre_interval_s

    def _kept_by_saturation(self, state: DriftCompState, limits: list[float]) -> bool:
        """The controller reports an axis saturated that the books, since a
        re-centre booked as released, put below half its limit: it kept the
        displacement."""
        return any(state.saturated[k] and abs(self._comp_q[k]) < 0.5 * limits[k] for k in range(2))

    def recentre_checked(self, *, kept: bool = False) -> None:
        """The frame after the last re-centre confirmed it (the daemon's check);
        with ``kept``, that frame (or a saturation the books cannot explain)
        showed a controller that kept a displacement booked as released: it
        is booked now, as an ``offset_move``, so ``get_offset()`` and the
        event log are right again from here on (frames in between were
        measured on the wrong books), ramped out over the next interval,
        and later re-centres do not switch (``release = "keep"``)."""
        rc = self._unchecked
        self._unchecked = None
        if rc is None or not kept or rc.procedure != "release":
            return
        self.release = "keep"
        qx, qy = rc.displacement_nm
        self._comp_q = [self._comp_q[0] + qx, self._comp_q[1] + qy]
        self._unwind = (self._unwind[0] + qx, self._unwind[1] + qy)
        self._events.append(Event(max(self._comp_t, rc.t_s), EventKind.OFFSET_MOVE, qx, qy))
        log.warning(
            "drift compensation: the controller kept the displacement through off/on at the "
            "re-centre at t = %.1f s, booked as released; (%.2f, %.2f) nm booked now, and "
            "re-centres no longer switch it (release = keep)",
            rc.t_s, qx, qy,
        )  # fmt: skip

    async def probe(self, dx_nm: float, dy_nm: float, *, exact: bool = False) -> None:
        """Check the actuator: the frame centre moves by ``(dx, dy)`` and the
        compensation ramps the same back out over the next interval between
        velocity commands, booked as net zero (a take-over like a ramp
        re-centre's, :class:`Recentre` ``kind = "probe"``; at most half the
        re-centre threshold, and unless ``exact``, of the sign that leaves
        the compensation nearer zero). A compensation
        that applies ``g`` times what is asked leaves the image
        ``(1 − g)·(dx, dy)`` off, which the frame after it shows."""
        for name, v in (("dx_nm", dx_nm), ("dy_nm", dy_nm)):
            if not math.isfinite(v):
                raise ValueError(f"probe: {name} = {v} is not finite")
        if self._comp_on:
            self._book_comp(await self.now_s())
        # At most half the re-centre threshold, and the sign that leaves the
        # compensation nearer zero once it has ramped the probe out.
        size = math.hypot(dx_nm, dy_nm)
        room = 0.5 * self.recentre_fraction * self.drift_comp_limit_pct / 100.0
        cap = room * min(self._range_nm)
        scale = min(1.0, cap / size) if size > 0 else 0.0
        if not exact and dx_nm * self._comp_q[0] + dy_nm * self._comp_q[1] < 0:
            scale = -scale
        await self._take_over((scale * dx_nm, scale * dy_nm), "ramp", "probe")

    async def _recentre(self) -> None:
        # Stop the ramp first (the displacement holds), so the frame centre
        # takes over exactly what was applied; then release it (a controller
        # known to reset it), or leave it booked and ramp it out over the
        # next interval.
        await self._switch_velocity(1, (0.0, 0.0))
        procedure: Literal["release", "ramp"] = "release" if self.release == "reset" else "ramp"
        await self._take_over((self._comp_q[0], self._comp_q[1]), procedure, "recentre")

    async def _take_over(
        self,
        q: tuple[float, float],
        procedure: Literal["release", "ramp"],
        kind: Literal["recentre", "probe"],
    ) -> None:
        """The frame centre moves by ``q``; the compensation gives it up by
        ``procedure`` (see :class:`Recentre`)."""
        qx, qy = q
        log.info("drift compensation: %s by (%.2f, %.2f) nm (%s)", kind, qx, qy, procedure)
        if self.offset_mode == "frame":
            cx, cy, w, h, angle = await self.call("Scan.FrameGet")
            await self.call("Scan.FrameSet", cx + qx / _M_TO_NM, cy + qy / _M_TO_NM, w, h, angle)
        else:
            x, y = await self.call("FolMe.XYPosGet", 0)
            await self.call("FolMe.XYPosSet", x + qx / _M_TO_NM, y + qy / _M_TO_NM, 0)
        t = self._comp_t
        self._events.append(Event(t, EventKind.OFFSET_MOVE, qx, qy))
        if procedure == "release":
            await self._switch_velocity(2, (0.0, 0.0))
            t = self._comp_t
            # The base took over what the compensation had applied: net zero.
            self._events.append(Event(t, EventKind.OFFSET_MOVE, -qx, -qy))
            self._comp_q = [0.0, 0.0]
        else:
            self._unwind = (self._unwind[0] + qx, self._unwind[1] + qy)
        rc = Recentre(t, (qx, qy), procedure, kind)
        self.recentre_log.append(rc)
        self._unchecked = rc
        if kind == "recentre":
            self.recentres += 1

    # ---------------------------------------------------------------- scan control

    async def scanning(self) -> bool:
        """``Scan.StatusGet``."""
        (status,) = await self.call("Scan.StatusGet")
        return bool(status)

    async def start_scan(self, *, up: bool = True) -> None:
        """``Scan.Action`` start."""
        await self.call("Scan.Action", 0, 1 if up else 0)

    async def stop_scan(self) -> None:
        await self.call("Scan.Action", 1, 1)

"""Byte transports: where the driver's lines and frame blocks travel.

A driver never owns a port; it receives a :class:`Transport`. The base class
does the framing, buffering, timeouts and logging (read a line, read exactly n
bytes, write, flush); a subclass fills in only the raw hooks (open, close, read
whatever is available, write everything).

* :class:`SerialTransport` is built on :func:`serial.serial_for_url`, so a real
  port (``/dev/ttyUSB0``), a pseudo-terminal (``/dev/pts/5``) and loopback TCP
  (``socket://127.0.0.1:5025``) all go through the same code.
* :class:`ScriptedTransport` plays a table of (command, reply) pairs, for
  protocol tests in the style of pymeasure's ``expected_protocol``.

Transports are blocking and meant to be driven from one worker thread at a
time (the async driver calls them through :func:`asyncio.to_thread` while it
holds its per-connection lock).
"""

from __future__ import annotations

import abc
import contextlib
import logging
import math
import socket
import time
from collections import deque
from collections.abc import Iterable
from typing import Any

from afmdrift.drivers._protocol import (
    LINE_MAX,
    InstrumentDisconnected,
    InstrumentTimeout,
    ProtocolError,
)

__all__ = ["ScriptedTransport", "SerialTransport", "Transport"]

log = logging.getLogger(__name__)

_LOG_BYTES = 120  # bytes of each transfer shown in debug logs


def _shown(data: bytes) -> str:
    if len(data) <= _LOG_BYTES:
        return repr(data)
    return f"{data[:_LOG_BYTES]!r}... ({len(data)} bytes)"


class Transport(abc.ABC):
    """Framing, buffering, timeouts and logging over raw byte I/O.

    Parameters
    ----------
    name : str
        Shown in log lines and error messages (usually the URL).
    max_line : int
        Longest accepted line in bytes; a longer one raises :class:`ProtocolError`.
    """

    def __init__(self, *, name: str, max_line: int = LINE_MAX) -> None:
        self.name = name
        self.max_line = max_line
        self._buffer = bytearray()
        self._open = False
        #: ``time.monotonic()`` when bytes last arrived (``-inf`` before any).
        self.last_rx_s = -math.inf

    # ---------------------------------------------------------------- raw hooks

    @abc.abstractmethod
    def _open_raw(self) -> None:
        """Open the connection; raise :class:`InstrumentDisconnected` on failure."""

    @abc.abstractmethod
    def _close_raw(self) -> None:
        """Close the connection (idempotent, never raises)."""

    @abc.abstractmethod
    def _write_raw(self, data: bytes) -> None:
        """Write all of ``data``; raise :class:`InstrumentDisconnected` if the line is gone."""

    @abc.abstractmethod
    def _read_raw(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return 1..max_bytes bytes, or ``b""`` when nothing arrived within ``timeout_s``.

        Raise :class:`InstrumentDisconnected` when the peer closed the line.
        """

    # ---------------------------------------------------------------- public API

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        """Open (or re-open) the connection with an empty input buffer."""
        if self._open:
            return
        self._buffer.clear()
        self._open_raw()
        self._open = True
        log.debug("%s: opened", self.name)

    def close(self) -> None:
        """Close the connection; safe to call twice."""
        if self._open:
            log.debug("%s: closed", self.name)
        self._open = False
        self._buffer.clear()
        self._close_raw()

    def _require_open(self) -> None:
        if not self._open:
            raise InstrumentDisconnected(f"{self.name}: transport is not open")

    def write(self, data: bytes) -> None:
        """Write ``data`` completely."""
        self._require_open()
        log.debug("%s <- %s", self.name, _shown(data))
        try:
            self._write_raw(data)
        except InstrumentDisconnected:
            self._open = False
            raise

    def _fill(self, max_bytes: int, deadline: float, what: str) -> None:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise InstrumentTimeout(f"{self.name}: timed out waiting for {what}")
        try:
            chunk = self._read_raw(max_bytes, remaining)
        except InstrumentDisconnected:
            self._open = False
            raise
        if chunk:
            self.last_rx_s = time.monotonic()
        self._buffer += chunk

    def read_line(self, timeout_s: float) -> bytes:
        """Read up to and including the next ``\\n``.

        Raises
        ------
        InstrumentTimeout
            No complete line within ``timeout_s``; bytes read so far stay buffered.
        ProtocolError
            More than ``max_line`` bytes without a terminator (they are discarded).
        """
        self._require_open()
        deadline = time.monotonic() + timeout_s
        scanned = 0
        while True:
            end = self._buffer.find(b"\n", scanned)
            if end >= 0:
                line = bytes(self._buffer[: end + 1])
                del self._buffer[: end + 1]
                log.debug("%s -> %s", self.name, _shown(line))
                return line
            scanned = len(self._buffer)
            if scanned > self.max_line:
                self._buffer.clear()
                raise ProtocolError(f"{self.name}: line longer than {self.max_line} bytes")
            self._fill(self.max_line, deadline, "a reply line")

    def read_exact(self, n: int, timeout_s: float) -> bytes:
        """Read exactly ``n`` bytes (a binary block) within ``timeout_s``."""
        self._require_open()
        deadline = time.monotonic() + timeout_s
        while len(self._buffer) < n:
            self._fill(n - len(self._buffer), deadline, f"{n} bytes of a block")
        data = bytes(self._buffer[:n])
        del self._buffer[:n]
        log.debug("%s -> block of %d bytes", self.name, n)
        return data

    def flush_input(self, *, quiet_s: float = 0.05, max_s: float = 2.0) -> int:
        """Discard buffered input and whatever arrives until the line is quiet.

        Reads until nothing arrives for ``quiet_s`` (at most ``max_s`` in all),
        so the tail of a garbled or late reply does not poison the next query.
        Returns the number of bytes discarded.
        """
        self._require_open()
        dropped = len(self._buffer)
        self._buffer.clear()
        stop = time.monotonic() + max_s
        while time.monotonic() < stop:
            try:
                chunk = self._read_raw(1 << 16, quiet_s)
            except InstrumentDisconnected:
                self._open = False
                raise
            if not chunk:
                break
            dropped += len(chunk)
        if dropped:
            log.info("%s: discarded %d bytes to resynchronise", self.name, dropped)
        return dropped

    @property
    def buffered(self) -> int:
        """Bytes received but not yet consumed."""
        return len(self._buffer)


class SerialTransport(Transport):
    """A transport on :func:`serial.serial_for_url`.

    Parameters
    ----------
    url : str
        ``/dev/ttyUSB0``, ``/dev/pts/5`` or ``socket://127.0.0.1:5025``.
    baudrate : int
        Line speed for real ports (ignored by ``socket://``; a pty accepts any).
    write_timeout_s : float
        Longest a write may block before :class:`InstrumentTimeout`.
    """

    def __init__(self, url: str, *, baudrate: int = 115200, write_timeout_s: float = 10.0) -> None:
        super().__init__(name=url)
        self.url = url
        self.baudrate = baudrate
        self.write_timeout_s = write_timeout_s
        self._port: Any = None  # serial.Serial (untyped library)

    def _open_raw(self) -> None:
        import serial

        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=0.1,
                write_timeout=self.write_timeout_s,
            )
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as err:
            raise InstrumentDisconnected(f"{self.url}: cannot open: {err}") from None
        self._port = port

    def _close_raw(self) -> None:
        port, self._port = self._port, None
        if port is None:
            return
        sock = getattr(port, "_socket", None)
        if type(port).__module__ == "serial.urlhandler.protocol_socket" and sock is not None:
            # pyserial's socket:// close() sleeps 0.3 s ("give the server some
            # time") and skips socket.close() when shutdown() fails, as it does
            # once the peer has gone; a driver that reopens its line to drop an
            # endless reply cannot afford the one nor the other.
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()
            port._socket = None
            port.is_open = False
            return
        try:
            port.close()
        except OSError as err:
            log.warning("%s: error while closing: %s", self.url, err)
        if sock is not None:
            sock.close()

    def _serial(self) -> Any:
        if self._port is None:
            raise InstrumentDisconnected(f"{self.url}: transport is not open")
        return self._port

    def _write_raw(self, data: bytes) -> None:
        import serial

        port = self._serial()
        try:
            port.write(data)
            port.flush()
        except serial.SerialTimeoutException:
            raise InstrumentTimeout(
                f"{self.url}: write of {len(data)} bytes timed out after {self.write_timeout_s} s"
            ) from None
        except (serial.SerialException, OSError) as err:
            raise InstrumentDisconnected(f"{self.url}: write failed: {err}") from None

    def _read_raw(self, max_bytes: int, timeout_s: float) -> bytes:
        import serial

        port = self._serial()
        try:
            # Wait for the first byte, then take whatever else is already there
            # (``in_waiting`` is at most 1 for socket://, so it cannot size the read).
            port.timeout = max(timeout_s, 0.0)
            data: bytes = port.read(1)
            if data and max_bytes > 1:
                port.timeout = 0
                data += port.read(max_bytes - 1)
        except (serial.SerialException, OSError) as err:
            raise InstrumentDisconnected(f"{self.url}: read failed: {err}") from None
        return data


class ScriptedTransport(Transport):
    """Plays a protocol table: a list of ``(command, reply)`` byte pairs.

    Each write must equal the next pair's command (terminator included);
    its reply (may be ``b""`` for none) then becomes readable. A pair whose
    command is ``None`` makes its reply readable at once, before the next
    write: stale or unsolicited bytes already on the line. When a write does
    not match, :class:`AssertionError` names the pair.

    After the exchange, :meth:`assert_done` checks that every pair was used and
    nothing is left unread, as pymeasure's ``expected_protocol`` does.
    """

    def __init__(
        self, pairs: Iterable[tuple[bytes | None, bytes]], *, name: str = "script"
    ) -> None:
        super().__init__(name=name)
        self._pairs: deque[tuple[bytes | None, bytes]] = deque(pairs)
        self._pending = bytearray()
        self.opens = 0
        self._release_unsolicited()

    def _release_unsolicited(self) -> None:
        while self._pairs and self._pairs[0][0] is None:
            self._pending += self._pairs.popleft()[1]

    def _open_raw(self) -> None:
        self.opens += 1

    def _close_raw(self) -> None:
        return None

    def _write_raw(self, data: bytes) -> None:
        if not self._pairs:
            raise AssertionError(f"unexpected write {data!r}: the protocol table is exhausted")
        expected, reply = self._pairs.popleft()
        if data != expected:
            raise AssertionError(f"wrote {data!r}, the protocol table expected {expected!r}")
        self._pending += reply
        self._release_unsolicited()

    def _read_raw(self, max_bytes: int, timeout_s: float) -> bytes:
        if not self._pending:
            time.sleep(timeout_s)  # a real line would wait this long too
            return b""
        data = bytes(self._pending[:max_bytes])
        del self._pending[:max_bytes]
        return data

    def assert_done(self) -> None:
        """Every pair was used and no reply byte is left unread."""
        if self._pairs:
            raise AssertionError(f"{len(self._pairs)} protocol pair(s) unused: {list(self._pairs)}")
        left = bytes(self._pending) + bytes(self._buffer)
        if left:
            raise AssertionError(f"{len(left)} reply byte(s) left unread: {left[:80]!r}")

"""Fuzzing the instrument link end to end: a fake instrument on loopback TCP
answers the production driver with arbitrary bytes, and the driver raises only
the typed errors the daemon handles (``INSTRUMENT_ERRORS``), never anything
else, and never hangs past its timeouts."""

from __future__ import annotations

import asyncio
import re
import socket
import threading
import time
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmdrift.drivers import NanoScopeDriver
from afmdrift.service import INSTRUMENT_ERRORS

_TAG = re.compile(rb"^@(\d+) ")


class FakeInstrument:
    """A TCP server on 127.0.0.1 that answers each command line with a script.

    ``reply(tag)`` gives the bytes to send for the request tagged ``tag``;
    the tag lets fuzzed replies sometimes look like real ones.
    """

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = int(self.sock.getsockname()[1])
        self.payload = b""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(0.5)
                buf = b""
                try:
                    while not self._stop.is_set():
                        chunk = conn.recv(4096)
                        if not chunk:
                            break
                        buf += chunk
                        while b"\n" in buf:
                            line, buf = buf.split(b"\n", 1)
                            m = _TAG.match(line)
                            tag = m.group(1) if m else b"1"
                            conn.sendall(self.payload.replace(b"@T", b"@" + tag))
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self._thread.join(2.0)


@pytest.fixture(scope="module")
def fake() -> Iterator[FakeInstrument]:
    server = FakeInstrument()
    yield server
    server.close()


_lines = st.one_of(
    st.binary(max_size=200),
    st.sampled_from(
        [
            b"@T SYST:TIME 12.5\n",
            b"@T SYST:TIME nan\n",
            b"@T SYST:TIME 1e999\n",
            b"@T EVENT:LOG 0,3\n@T EVENT 0,1.0,power_on,0,0\n",
            b"@T EVENT:LOG 0,1000000000\n",
            b"@T EVENT:LOG 0,1\n@T EVENT 0,1.0,door_slam,0,0\n",
            b"@T #FRAME 0,0,0,0,0,0,0,0,0\n",
            b"@T #FRAME 1,99999,99999,1,1,0,1,up,f4,0\n",
            b"@T ERR -113,Undefined header\n",
            b"@T OK\n",
            b"@T *IDN ACME,AFM,1,2\n",
            b"\xff\xfe\x00\n",
            b"@99999999999999999999 OK\n",
        ]
    ),
).map(lambda b: b if b.endswith(b"\n") else b + b"\n")

_calls = st.sampled_from(
    ["identify", "now_s", "latest_frame", "read_channels", "events", "get_offset"]
)


@pytest.mark.slow
@settings(
    max_examples=80,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(payload=st.lists(_lines, min_size=1, max_size=4).map(b"".join), call=_calls)
def test_fuzz_driver_over_loopback_raises_only_instrument_errors(
    fake: FakeInstrument, payload: bytes, call: str
) -> None:
    fake.payload = payload

    async def run() -> None:
        driver = NanoScopeDriver(
            f"socket://127.0.0.1:{fake.port}",
            timeout_s=0.2,
            frame_timeout_s=0.3,
            reconnect_attempts=1,
            backoff_initial_s=0.01,
        )
        try:
            await driver.connect()
            fn = getattr(driver, call)
            await (fn(0) if call == "events" else fn())
        except INSTRUMENT_ERRORS:
            pass  # the typed errors the daemon handles
        finally:
            await driver.close()

    started = time.monotonic()
    asyncio.run(run())
    assert time.monotonic() - started < 10.0  # bounded by the driver's timeouts

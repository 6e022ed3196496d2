"""Vendor-client conformance: the official Nanonis Python client drives the simulator.

``nanonis-spm`` (SPECS Zurich) is a test-only dependency, the optional extra
``nanonis-test``, which ``make install`` (and so CI) installs from PyPI; its
licence restricts redistribution, so nothing of it is in this repository.
Without it the test is skipped, unless ``AFMDRIFT_REQUIRE_NANONIS_SPM=1`` (set
by ``.ci/run``), which makes the missing client a failure.
"""

from __future__ import annotations

import asyncio
import os
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from afmdrift.drivers.sim import PIEZO_RANGE_NM, SimulatedAFM
from afmdrift.drivers.sim._nanonis_server import (
    CLOCK_SIGNAL,
    SCAN_CHANNEL,
    SIGNAL_NAMES,
    NanonisSimServer,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service_sim import small_scenario

if os.environ.get("AFMDRIFT_REQUIRE_NANONIS_SPM") == "1":
    # CI (.ci/run) installs the extra with `make install`: a missing client is
    # a failure there, not a skip that would hide this test for good.
    import nanonis_spm
else:
    nanonis_spm = pytest.importorskip(
        "nanonis_spm",
        reason="the official client nanonis-spm is not installed "
        "(pip install -c constraints.txt -e '.[nanonis-test]')",
    )

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]


def _values(reply: tuple[Any, ...]) -> list[Any]:
    """The decoded variables of a nanonis-spm reply, after checking it carried no error."""
    error, _raw, variables = reply
    assert error == "", f"the controller reported {error!r}"
    return list(variables)


async def test_the_official_client_reads_what_the_simulator_holds() -> None:
    sim = SimulatedAFM(small_scenario(seed=11, drift_nm_per_sqrt_s=0.0))
    async with NanonisSimServer(sim, speed=100.0) as server:
        port = await server.start_tcp(0)
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        client = nanonis_spm.Nanonis(sock)

        async def call(fn: Callable[..., tuple[Any, ...]], *args: Any) -> list[Any]:
            return _values(await asyncio.to_thread(fn, *args))

        try:
            width, height = sim.scan_size_nm
            ox, oy = sim.get_offset()
            cx, cy, w, h, angle = await call(client.Scan_FrameGet)
            assert (cx, cy) == pytest.approx(((ox + width / 2) * 1e-9, (oy + height / 2) * 1e-9))
            assert (w, h, angle) == pytest.approx((width * 1e-9, height * 1e-9, 0.0))

            n, channels, pixels, lines = await call(client.Scan_BufferGet)
            assert (n, [c[0] for c in channels]) == (1, [SCAN_CHANNEL])
            assert (pixels, lines) == sim.pixels

            _vf, _vb, fwd, bwd, keep, _ratio = await call(client.Scan_SpeedGet)
            assert fwd + bwd == pytest.approx(1.0 / sim.line_rate_hz, rel=1e-6)
            assert keep == 1

            (status,) = await call(client.Scan_StatusGet)
            assert status == 1

            timed_out, path_size, path = await call(client.Scan_WaitEndOfScan, 20_000)
            assert (timed_out, path_size, path) == (0, 0, "")
            name_size, name, rows, cols, data, up = await call(
                client.Scan_FrameDataGrab, SCAN_CHANNEL, 1
            )
            frame = sim.latest_frame()
            assert frame is not None
            assert (name_size, name) == (len("Z (m)"), "Z (m)")
            assert (rows, cols) == frame.shape
            np.testing.assert_allclose(np.asarray(data) * 1e9, frame.heights_nm, atol=1e-4)
            assert up == (1 if frame.direction.value == "up" else 0)

            await call(client.FolMe_XYPosSet, np.float64(cx + 20e-9), np.float64(cy), np.uint32(0))
            x, y = await call(client.FolMe_XYPosGet, np.uint32(0))
            assert (x, y) == pytest.approx((cx + 20e-9, cy), abs=1e-15)
            assert sim.tip_position_nm == pytest.approx((width / 2 + 20.0, height / 2), abs=1e-4)

            await call(
                client.Piezo_DriftCompSet,
                np.uint32(1),
                np.float32(2e-10),
                np.float32(-1e-10),
                np.float32(0),
                np.float32(5),
            )
            on, vx, vy, vz, sx, sy, sz, limit = await call(client.Piezo_DriftCompGet)
            assert (on, sx, sy, sz, limit) == (1, 0, 0, 0, 5.0)
            assert (vx, vy, vz) == pytest.approx((2e-10, -1e-10, 0.0), rel=1e-6)
            assert sim.drift_compensation()[0]
            assert sim.drift_compensation()[3] * PIEZO_RANGE_NM[0] / 100 == 500.0

            size, count, names = await call(client.Signals_NamesGet)
            assert names == list(SIGNAL_NAMES)
            assert count == len(SIGNAL_NAMES)
            assert size == sum(4 + len(s) for s in SIGNAL_NAMES)

            clock = SIGNAL_NAMES.index(CLOCK_SIGNAL)
            temperature = SIGNAL_NAMES.index("Temperature (C)")
            count, values = await call(client.Signals_ValsGet, [clock, temperature], np.uint32(0))
            assert count == 2
            t_s, temp_c = (v[0] for v in values)
            assert t_s == pytest.approx(sim.now_s, abs=5.0)
            assert 10.0 < temp_c < 40.0
        finally:
            sock.close()

"""Another instrument takes over the daemon's address (issue 42).

The daemon follows a loopback simulator; the simulator is killed and another
one, with another serial and another pixel size, answers on the same port.
The daemon must say so, start a new chain of positions whose reference
position is estimated (never measured across the two instruments, so never
taken for drift), and the new chain must follow its own measured increments
with σ the root-sum-square of the estimate's and the chain's own.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import (
    SimProcess,
    driver,
    running_service,
    scenario_data,
    service_config,
    write_scenario,
)

from afmdrift.client import Subscriber
from afmdrift.pipeline import FrameRecord
from afmdrift.service import RunStore
from afmdrift.wire import FrameMsg, ModelMsg, OffsetMsg

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]

#: Frames measured in the new chain before the test looks.
NEW_FRAMES = 10


def _behind_increments_nm(chain: list[FrameRecord]) -> np.ndarray:
    """|p_k − p_ref − Σ increments| of each frame after ``chain[0]`` (the
    chain's reference; stored ``x_nm, y_nm`` and ``dx_nm, dy_nm``), nm."""
    p = np.array([[r.x_nm, r.y_nm] for r in chain])
    steps = np.cumsum([[r.dx_nm, r.dy_nm] for r in chain[1:]], axis=0)
    return np.hypot(*(p[1:] - p[0] - steps).T)


async def test_another_instrument_on_the_address_starts_a_new_chain(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ctx = zmq.asyncio.Context()
    run = tmp_path / "run"
    first = scenario_data(seed=7)  # serial sim-service-test-7, 4 nm/px
    other = scenario_data(seed=8)  # serial sim-service-test-8 ...
    other["scan"]["size_nm"] = [3.0 * 128, 3.0 * 128]  # ... at 3 nm/px
    sim = SimProcess(write_scenario(tmp_path / "first.toml", first), speed=100.0)
    messages: list[FrameMsg | ModelMsg | OffsetMsg] = []

    async def listen(sub: Subscriber) -> None:
        while True:
            msg = await sub.recv()
            if isinstance(msg, FrameMsg | ModelMsg | OffsetMsg):
                messages.append(msg)

    caplog.set_level(logging.WARNING, logger="afmdrift.service")
    try:
        url = sim.start()
        async with running_service(service_config(run), driver(url), ctx) as service:
            sub = Subscriber(service.pub_endpoint, topics=("frame", "model", "offset"), ctx=ctx)
            listener = asyncio.create_task(listen(sub))
            try:
                async with asyncio.timeout(30):
                    await service.wait_for_frames(5)
                sim.kill()
                async with asyncio.timeout(10):
                    await service.wait_for_flag("instrument_error")
                assert "instrument_changed" not in service.status_msg().flags
                before = service.frames_processed
                sim = SimProcess(
                    write_scenario(tmp_path / "other.toml", other), speed=100.0, port=sim.port
                )
                assert sim.start() == url
                async with asyncio.timeout(60):
                    await service.wait_for_frames(before + 1 + NEW_FRAMES)
                assert "instrument_changed" in service.status_msg().flags
            finally:
                listener.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await listener
                sub.close()
    finally:
        sim.kill()
        ctx.term()

    # the daemon said so, naming both instruments
    said = [r.getMessage() for r in caplog.records if "instrument changed" in r.getMessage()]
    assert len(said) == 1, said
    assert (
        "(serial sim-service-test-7) -> afmdrift SimulatedAFM (serial sim-service-test-8)"
        in (said[0])
    )

    with RunStore(run) as store:
        records = store.frames()
    start = next(k for k, r in enumerate(records) if r.pixel_x_nm == 3.0)
    old, new = records[:start], records[start:]
    assert all(r.pixel_x_nm == 4.0 for r in old)
    assert len(new) >= 1 + NEW_FRAMES
    ref = new[0]
    # the step between the instruments is not measured: the new chain's
    # reference has no increment, and its position is an estimate with its σ
    assert ref.reason == "new reference (position estimated)"
    assert math.isnan(ref.dx_nm)
    assert math.isnan(ref.dy_nm)
    assert not ref.fed_model
    assert math.isfinite(ref.sigma_nm)
    assert ref.sigma_nm > 0.0
    assert all(r.fed_model and not r.reason for r in new[1:]), [r.reason for r in new[1:]]
    # no increment in the whole run holds a step (the drift moves < 1 nm a frame)
    steps = [math.hypot(r.dx_nm, r.dy_nm) for r in records if math.isfinite(r.dx_nm)]
    assert max(steps) < 2.0, steps
    # the new chain follows its own increments as closely as the first chain
    # does its (the trajectory at mid-scan time is not the sum of the
    # registration's increments), and does not fall behind them
    behind_old = _behind_increments_nm(old)
    behind_new = _behind_increments_nm(new)
    print(f"behind the increments: first chain {behind_old}, new chain {behind_new}")
    assert behind_new.max() < max(0.1, 2.0 * behind_old.max())
    # σ: the estimate's and the chain's own, in root-sum-square
    own = np.sqrt([r.sigma_nm**2 - ref.sigma_nm**2 for r in new[1:]])
    print(f"σ of the estimate {ref.sigma_nm:.4f} nm, of the chain's own {own}")
    assert np.all(own < 3.0 * max(r.sigma_nm for r in old[1:]))

    # on the wire: the chain number goes up once, where the new instrument starts
    frames = [m for m in messages if isinstance(m, FrameMsg)]
    chains = [m.chain for m in frames]
    assert chains == sorted(chains)
    assert set(chains) == {0, 1}
    assert all(m.chain == 1 for m in frames if m.frame >= ref.seq)
    assert all(m.chain == 0 for m in frames if m.frame < ref.seq)
    assert {m.chain for m in messages if isinstance(m, OffsetMsg | ModelMsg)} == {0, 1}

"""The scan geometry changes under the daemon: frames of another size now and
then, and a zoom in and back out. A second client (a user's script) changes
the scan over the same protocol while the daemon runs; the drift position of
every frame must stay on the simulator's true drift (never sent over the wire).

Regression: every third frame at 100x150 px among 128x128 ones made 18
re-references in an outside test, and the drift position ended 44 nm off the
truth, an error carried into every later offset.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import driver, running_service, service_config, sim_server, small_scenario

from afmdrift.drivers import Frame, NanoScopeDriver, ScanDirection
from afmdrift.model import truth_frame_mean
from afmdrift.service import RunStore

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]

#: Drift position error allowed against the truth (the issue's limit).
LIMIT_NM = 2.0


async def _next_frames(user: NanoScopeDriver, n: int) -> None:
    """Wait until the instrument completed ``n`` more frames."""
    target = await user.frame_index() + n
    for _ in range(5000):  # polled: the instrument has no frame notification
        if await user.frame_index() >= target:
            return
        await asyncio.sleep(0.02)
    raise TimeoutError(f"the instrument did not complete {n} more frames")


async def _rescan(
    user: NanoScopeDriver,
    *,
    pixels: tuple[int, int] | None = None,
    size_nm: tuple[float, float] | None = None,
) -> None:
    await user.stop_scan()
    await user.configure_scan(pixels=pixels, size_nm=size_nm)
    await user.start_scan()


def _errors_nm(sim: object, records: list) -> list[float]:  # type: ignore[type-arg]
    """|p − truth| of every valid record, truth relative to the first (reference) frame."""
    t0, t1 = records[0].t_start_s, records[-1].t_end_s
    t = np.linspace(t0, t1, int((t1 - t0) / 0.25) + 2)
    x, y = sim.truth_at(t)  # type: ignore[attr-defined]
    table = (t, np.stack([x, y], axis=1))

    def truth(r) -> np.ndarray:  # type: ignore[no-untyped-def]
        like = Frame(
            index=0,
            heights_nm=np.zeros((r.rows, 1)),
            pixel_size_nm=(1.0, 1.0),
            t_start_s=r.t_start_s,
            t_end_s=r.t_end_s,
            direction=ScanDirection(r.direction),
        )
        return truth_frame_mean(like, *table)

    ref = truth(records[0])
    return [
        math.hypot(*(np.array([r.x_nm, r.y_nm]) - (truth(r) - ref))) for r in records if r.valid
    ]


async def _run(tmp_path: Path, script) -> tuple[list, list[float]]:  # type: ignore[no-untyped-def]
    ctx = zmq.asyncio.Context()
    run = tmp_path / "run"
    scenario = small_scenario(drift_nm_per_sqrt_s=0.05, warmup_nm=(40.0, -25.0))
    try:
        async with sim_server(scenario, speed=100.0) as (server, url):
            async with running_service(service_config(run), driver(url), ctx) as service:
                async with asyncio.timeout(30):
                    await service.wait_for_frames(3)
                user = driver(url)
                async with user, asyncio.timeout(120):
                    await script(user)
                    await _next_frames(user, 2)
                    target = service.frames_processed + 1
                    await service.wait_for_frames(target)
            records = RunStore(run).frames()
            return records, _errors_nm(server.sim, records)
    finally:
        ctx.term()


async def test_frames_of_another_size_now_and_then_keep_the_position(tmp_path: Path) -> None:
    async def every_third_frame_odd(user: NanoScopeDriver) -> None:
        for _ in range(6):
            await _next_frames(user, 2)
            await _rescan(user, pixels=(100, 150))
            await _next_frames(user, 1)
            await _rescan(user, pixels=(128, 128))

    records, errors = await _run(tmp_path, every_third_frame_odd)
    odd = [r for r in records if (r.cols, r.rows) == (100, 150)]
    assert len(odd) >= 4, "the odd-sized frames did not reach the daemon"
    new_refs = [r for r in records if r.reason.startswith("new reference")]
    # only the first odd-sized frame takes a reference of its own
    assert len(new_refs) == 1, [(r.seq, r.cols, r.rows) for r in new_refs]
    assert all(r.fed_model for r in odd[1:]), [r.reason for r in odd]
    assert max(errors) < LIMIT_NM, errors


async def test_a_zoom_in_and_back_out_keeps_the_position(tmp_path: Path) -> None:
    async def zoom(user: NanoScopeDriver) -> None:
        await _next_frames(user, 2)
        await _rescan(user, size_nm=(256.0, 256.0))  # 2 nm/px instead of 4
        await _next_frames(user, 4)
        await _rescan(user, size_nm=(512.0, 512.0))
        await _next_frames(user, 3)

    records, errors = await _run(tmp_path, zoom)
    zoomed = [r for r in records if r.pixel_x_nm == pytest.approx(2.0)]
    assert len(zoomed) >= 3, "the zoomed frames did not reach the daemon"
    after = [r for r in records if r.seq > zoomed[-1].seq]
    assert after, "no frame after the zoom out"
    # back at 4 nm/px the frames are measured against the first reference again
    assert all(r.fed_model and not r.reason for r in after), [r.reason for r in after]
    assert max(errors) < LIMIT_NM, errors

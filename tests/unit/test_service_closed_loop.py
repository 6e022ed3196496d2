"""The closed loop at a change of position chain (issue 42): it re-baselines
on the instrument's offset as it stands instead of moving the tip by the
step between two chains.

The real :class:`ClosedLoop`, link, acquisition and publishing, against a
scripted instrument that keeps the offset it was sent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from service_sim import service_config

from afmdrift.model import OffsetCurve
from afmdrift.pipeline import FramePipeline
from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo
from afmdrift.service._acquire import Acquisition
from afmdrift.service._closed_loop import ClosedLoop
from afmdrift.service._link import InstrumentLink
from afmdrift.service._publish import Publishing
from afmdrift.wire import OffsetMsg


class OffsetInstrument:
    """Answers with the offset it was last sent, and counts the moves."""

    def __init__(self, offset_nm: tuple[float, float]) -> None:
        self.offset_nm = offset_nm
        self.moves: list[tuple[float, float]] = []

    async def connect(self) -> None: ...

    async def close(self) -> None: ...

    async def identify(self) -> InstrumentInfo:
        return InstrumentInfo("test", "scripted", "0", "1")

    async def now_s(self) -> float:
        return 10.0

    async def latest_frame(self) -> Frame | None:
        return None

    async def read_channels(self) -> ChannelSample:
        return ChannelSample(10.0, {})

    async def events(self, start: int = 0) -> list[Event]:
        return []

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        self.offset_nm = (x_nm, y_nm)
        self.moves.append((x_nm, y_nm))

    async def get_offset(self) -> tuple[float, float]:
        return self.offset_nm


class _Loop:
    def __init__(self, tmp_path: Path, inst: OffsetInstrument) -> None:
        cfg = service_config(tmp_path, closed_loop=True)
        link = InstrumentLink(inst, reconnect_delay_s=0.01, flags=set())
        link.connected.set()
        self.publishing = Publishing(cfg.service, clock=link.clock, flags=link.flags)
        self.publishing.curve = OffsetCurve(
            kind="hermite", t_valid_s=(0.0, 1.0), knot_t_s=np.zeros(1),
            knot_nm=np.zeros((1, 2)), slope_nm_per_s=np.zeros((1, 2)),
        )  # fmt: skip
        pipeline = FramePipeline(config=cfg)
        pipeline.positions.t_ref_s = 0.0
        self.loop = ClosedLoop(
            cfg.service, link=link, acquisition=Acquisition(link, cfg.service),
            publishing=self.publishing, pipeline=pipeline,
        )  # fmt: skip
        self.loop.connected(10.0, inst.offset_nm)

    async def tick(self, d_nm: tuple[float, float], *, chain: int = 0) -> None:
        self.publishing.chain = chain
        self.publishing.last_offset = OffsetMsg(
            seq=0, t_s=10.0, wall_s=0.0, x_nm=d_nm[0], y_nm=d_nm[1], valid=True, chain=chain
        )
        await self.loop.tick()


@pytest.mark.asyncio
async def test_a_new_chain_re_baselines_instead_of_moving_by_the_step(tmp_path: Path) -> None:
    """d steps by 20 nm where the chain changes (a value of another chain):
    the tip stays, and follows d's later changes from there."""
    inst = OffsetInstrument((100.0, 50.0))
    loop = _Loop(tmp_path, inst)
    await loop.tick((5.0, 1.0))
    assert inst.moves == [(105.0, 51.0)]
    await loop.tick((25.0, 1.0), chain=1)
    assert inst.moves == [(105.0, 51.0)]  # no move by the step
    await loop.tick((26.0, 3.0), chain=1)
    assert inst.moves[-1] == pytest.approx((106.0, 53.0))


@pytest.mark.asyncio
async def test_another_instrument_s_offset_is_taken_as_it_stands(tmp_path: Path) -> None:
    """Another instrument answers (ClosedLoop.rebaseline): its offset is not
    the one the hold was taken from, and the loop does not move it there."""
    inst = OffsetInstrument((100.0, 50.0))
    loop = _Loop(tmp_path, inst)
    await loop.tick((5.0, 1.0))
    inst.offset_nm = (-40.0, 7.0)  # the other instrument's offset
    loop.loop.connected(10.0, inst.offset_nm)
    loop.loop.rebaseline()
    await loop.tick((5.0, 1.0))
    assert inst.moves == [(105.0, 51.0)]
    await loop.tick((6.0, 1.0))
    assert inst.moves[-1] == pytest.approx((-39.0, 7.0))

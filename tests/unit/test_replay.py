"""ReplayInstrument: a recorded session played back through the Instrument interface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from afmdrift.config import DriverConfig, parse_config
from afmdrift.drivers import (
    Event,
    EventKind,
    Instrument,
    NanoScopeDriver,
    ReplayInstrument,
    ScanDirection,
    instrument_from_config,
)
from afmdrift.errors import ConfigError
from afmdrift.session import Session, SessionMeta, write_session

N_FRAMES = 4
PERIOD_S = 10.0  # frame i scans [10 i, 10 i + 6] s


class FakeWall:
    """A wall clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def session_dir(tmp_path: Path) -> Path:
    rng = np.random.default_rng(3)
    frames = rng.normal(size=(N_FRAMES, 16, 12)).astype(np.float32)
    times = np.array([[PERIOD_S * i, PERIOD_S * i + 6.0] for i in range(N_FRAMES)])
    session = Session(
        meta=SessionMeta(pixel_size_nm=(2.0, 3.0), line_time_s=6.0 / 16, start_time="", source="t"),
        frames=frames,
        frame_times=times,
        directions=[ScanDirection.UP, ScanDirection.DOWN] * (N_FRAMES // 2),
        channel_t_s=np.array([0.0, 40.0]),
        channels={"temperature_c": np.array([20.0, 24.0]), "humidity_pct": np.array([40.0, 40.0])},
        events=[
            Event(0.0, EventKind.POWER_ON),
            Event(12.0, EventKind.OFFSET_MOVE, 5.0, -5.0),
            Event(25.0, EventKind.MANIPULATION, 1.0, 2.0),
        ],
    )
    return write_session(session, tmp_path / "session")


@pytest.mark.asyncio
async def test_frames_complete_at_their_end_time(session_dir: Path) -> None:
    wall = FakeWall()
    replay = ReplayInstrument(session_dir, speed=2.0, clock=wall)
    assert isinstance(replay, Instrument)
    async with replay:
        assert await replay.now_s() == 0.0
        assert await replay.latest_frame() is None
        wall.t += 2.9  # virtual 5.8 s: frame 0 ends at 6 s
        assert await replay.latest_frame() is None
        wall.t += 0.1  # virtual 6.0 s
        f0 = await replay.latest_frame()
        assert f0 is not None
        assert (f0.index, f0.t_start_s, f0.t_end_s, f0.direction) == (0, 0.0, 6.0, "up")
        assert f0.pixel_size_nm == (2.0, 3.0)
        assert f0.shape == (16, 12)
        assert await replay.latest_frame() is f0
        wall.t += 10.0  # virtual 26 s: frames 0, 1 and 2 (ends at 26) are complete
        f2 = await replay.latest_frame()
        assert f2 is not None
        assert f2.index == 2
        np.testing.assert_array_equal(f2.heights_nm, replay.session.frames[2])
        assert not replay.finished
        wall.t += 100.0
        last = await replay.latest_frame()
        assert last is not None
        assert last.index == N_FRAMES - 1
        assert replay.finished


@pytest.mark.asyncio
async def test_channels_are_interpolated_at_now(session_dir: Path) -> None:
    wall = FakeWall()
    async with ReplayInstrument(session_dir, speed=1.0, clock=wall) as replay:
        wall.t += 10.0
        ch = await replay.read_channels()
        assert ch.t_s == 10.0
        assert ch.values["temperature_c"] == pytest.approx(21.0)
        assert ch.values["humidity_pct"] == pytest.approx(40.0)


@pytest.mark.asyncio
async def test_events_are_revealed_as_time_passes_and_offsets_logged(session_dir: Path) -> None:
    wall = FakeWall()
    async with ReplayInstrument(session_dir, speed=1.0, clock=wall) as replay:
        assert [e.kind for e in await replay.events()] == [EventKind.POWER_ON]
        wall.t += 15.0
        await replay.set_offset(3.0, 4.0)
        await replay.set_offset(3.0, 6.0)
        assert await replay.get_offset() == (3.0, 6.0)
        wall.t += 20.0
        log = await replay.events()
        assert [(e.t_s, e.kind, e.x_nm, e.y_nm) for e in log] == [
            (0.0, EventKind.POWER_ON, 0.0, 0.0),
            (12.0, EventKind.OFFSET_MOVE, 5.0, -5.0),
            (15.0, EventKind.OFFSET_MOVE, 3.0, 4.0),
            (15.0, EventKind.OFFSET_MOVE, 0.0, 2.0),  # deltas, as a controller logs them
            (25.0, EventKind.MANIPULATION, 1.0, 2.0),
        ]
        assert await replay.events(3) == log[3:]
        frame = await replay.latest_frame()
        assert frame is not None
        np.testing.assert_array_equal(frame.heights_nm, replay.session.frames[frame.index])


@pytest.mark.asyncio
async def test_as_fast_as_possible_gives_each_frame_once_in_order(session_dir: Path) -> None:
    async with ReplayInstrument(session_dir, speed=None) as replay:
        seen = []
        while not replay.finished:
            frame = await replay.latest_frame()
            assert frame is not None
            assert await replay.now_s() == frame.t_end_s
            seen.append(frame.index)
        assert seen == list(range(N_FRAMES))
        again = await replay.latest_frame()
        assert again is not None
        assert again.index == N_FRAMES - 1
        assert len(await replay.events()) == 3


@pytest.mark.asyncio
async def test_identify_names_the_session(session_dir: Path) -> None:
    info = await ReplayInstrument(session_dir).identify()
    assert (info.model, info.serial) == ("ReplayInstrument", "session")


def test_replay_rejects_bad_speed(session_dir: Path) -> None:
    with pytest.raises(ValueError, match="speed"):
        ReplayInstrument(session_dir, speed=-1.0)


def test_replay_url_in_driver_config(session_dir: Path) -> None:
    cfg = DriverConfig(transport=f"replay:{session_dir}", replay_speed=0)
    inst = instrument_from_config(cfg)
    assert isinstance(inst, ReplayInstrument)
    assert inst.speed is None
    serial = instrument_from_config(DriverConfig(transport="socket://127.0.0.1:5025"))
    assert isinstance(serial, NanoScopeDriver)


def test_driver_config_errors_name_key_and_range() -> None:
    with pytest.raises(ConfigError, match=r"driver.timeout_s = -1.0.*> 0"):
        parse_config({"driver": {"timeout_s": -1.0}})
    with pytest.raises(ConfigError, match="replay: needs a session directory"):
        parse_config({"driver": {"transport": "replay:"}})
    with pytest.raises(ConfigError, match=r"unknown key 'driver\.port'"):
        parse_config({"driver": {"port": 5025}})

"""The folder instrument: completeness, order, timing, sensor log, refusals."""

from __future__ import annotations

import asyncio
import os
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from afmdrift.config import DriverConfig, parse_config
from afmdrift.drivers import (
    FolderInstrument,
    InstrumentDisconnected,
    InstrumentError,
    OffsetNotSupportedError,
    instrument_from_config,
)
from afmdrift.drivers._folder import is_temporary_name
from afmdrift.errors import ConfigError
from afmdrift.io import write_sxm, write_tif
from afmdrift.records import Frame, ScanDirection

POLL_S = 0.05


def _image(seed: int, rows: int = 32, cols: int = 32) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(rows, cols))


async def _drain(inst: FolderInstrument, *, until: int, timeout_s: float = 10.0) -> list[Frame]:
    """Poll ``latest_frame`` as the service does until ``until`` frames came out."""
    frames: list[Frame] = []
    async with asyncio.timeout(timeout_s):
        while len(frames) < until:
            f = await inst.latest_frame()
            if f is not None and (not frames or f.index != frames[-1].index):
                frames.append(f)
            await asyncio.sleep(POLL_S / 2)
    return frames


def _tif(path: Path, seed: int, **kw: object) -> Path:
    return write_tif(path, _image(seed), pixel_size_nm=(2.0, 2.0), **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "temporary"),
    [
        ("scan001.sxm", False),
        ("scan001.sxm.tmp", True),
        (".scan001.sxm", True),
        ("scan001.sxm~", True),
        ("~scan001.sxm", True),
        ("scan001.sxm.part", True),
        ("scan001.sxm.crdownload", True),
        ("image.002", False),
    ],
)
def test_temporary_names(name: str, temporary: bool) -> None:
    assert is_temporary_name(name) is temporary


@pytest.mark.asyncio
async def test_existing_files_are_skipped_new_ones_read_in_time_order(tmp_path: Path) -> None:
    _tif(tmp_path / "old.tif", 0)
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, line_time_s=0.01)
    async with inst:
        assert await inst.latest_frame() is None
        # written in one scan period: ordered by header time, not name or arrival
        t0 = datetime.now().replace(microsecond=0)
        for name, seed, shift in (("b.tif", 1, 20.0), ("a.tif", 2, 30.0), ("c.tif", 3, 10.0)):
            start = datetime.fromtimestamp(t0.timestamp() - 60 + shift)
            _tif(tmp_path / name, seed, start=start, line_time_s=0.1)
        (tmp_path / "notes.txt").write_text("not an image")
        frames = await _drain(inst, until=3)
    assert inst.delivered == ["c.tif", "b.tif", "a.tif"]
    assert [f.index for f in frames] == [0, 1, 2]
    ends = [f.t_end_s for f in frames]
    assert ends == sorted(ends)
    # header times are trusted (they fit the mtime): 10 s apart, 32 lines of 0.1 s
    assert np.diff(ends) == pytest.approx([10.0, 10.0])
    assert frames[0].t_end_s - frames[0].t_start_s == pytest.approx(3.2)
    np.testing.assert_allclose(frames[0].heights_nm, _image(3).astype(np.float32))
    assert frames[0].pixel_size_nm == pytest.approx((2.0, 2.0))
    assert await inst.now_s() >= frames[-1].t_end_s


@pytest.mark.asyncio
async def test_bytes_appended_after_a_whole_image_do_not_give_the_frame_again(
    tmp_path: Path,
) -> None:
    """A writer whose last chunk only adds bytes after image data a reader had
    already accepted: the same frame again, later, would read as no drift. A
    file rewritten with other data is a new frame."""
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, line_time_s=0.01)
    async with inst:
        p = _tif(tmp_path / "x.tif", 1)
        (first,) = await _drain(inst, until=1)
        with p.open("ab") as f:
            f.write(b"\0" * 64)
        for _ in range(8):
            latest = await inst.latest_frame()
            assert latest is None or latest.index == first.index
            await asyncio.sleep(POLL_S)
        assert inst.delivered == ["x.tif"]
        _tif(p, 2)
        async with asyncio.timeout(10):
            while (latest := await inst.latest_frame()) is None or latest.index == first.index:  # noqa: ASYNC110 (polls as the service does)
                await asyncio.sleep(POLL_S / 2)
    assert inst.delivered == ["x.tif", "x.tif"]
    np.testing.assert_allclose(latest.heights_nm, _image(2).astype(np.float32))


@pytest.mark.asyncio
async def test_header_time_that_does_not_fit_the_mtime_is_replaced(tmp_path: Path) -> None:
    """A file copied from an old run keeps its duration but ends at its mtime."""
    inst = FolderInstrument(tmp_path, poll_s=POLL_S)
    async with inst:
        p = _tif(tmp_path / "x.tif", 0, start=datetime(2011, 1, 1), line_time_s=0.5)
        (frame,) = await _drain(inst, until=1)
    mtime = p.stat().st_mtime - inst.origin_s
    assert frame.t_end_s == pytest.approx(mtime)
    assert frame.t_end_s - frame.t_start_s == pytest.approx(16.0)


@pytest.mark.asyncio
async def test_without_header_timing_the_line_time_setting_is_used(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, line_time_s=0.25)
    async with inst:
        p = _tif(tmp_path / "x.tif", 0)
        (frame,) = await _drain(inst, until=1)
    assert frame.t_end_s == pytest.approx(p.stat().st_mtime - inst.origin_s)
    assert frame.line_time_s == pytest.approx(0.25)
    assert frame.direction is ScanDirection.UP


@pytest.mark.asyncio
async def test_overlapping_frames_are_moved_later(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, line_time_s=1.0)  # 32 s per frame
    async with inst:
        _tif(tmp_path / "a.tif", 0)
        _tif(tmp_path / "b.tif", 1)
        a, b = await _drain(inst, until=2)
    assert b.t_start_s >= a.t_end_s
    assert b.t_end_s - b.t_start_s == pytest.approx(32.0)


def _slow_writer(data: bytes, path: Path, *, chunks: int, pause_s: float) -> threading.Thread:
    def run() -> None:
        step = -(-len(data) // chunks)
        with path.open("wb") as f:
            for k in range(0, len(data), step):
                f.write(data[k : k + step])
                f.flush()
                os.fsync(f.fileno())
                time.sleep(pause_s)

    thread = threading.Thread(target=run)
    thread.start()
    return thread


@pytest.mark.parametrize(("suffix", "pause_s"), [(".sxm", 0.01), (".sxm", 0.15), (".tif", 0.15)])
@pytest.mark.asyncio
async def test_a_file_written_slowly_is_never_read_partially(
    tmp_path: Path, suffix: str, pause_s: float
) -> None:
    """Pauses shorter than the scan period: never even read before it is complete.
    Longer pauses: the stable partial file is read, refused by the reader and
    retried; the frame handed out is the whole file."""
    src = tmp_path / "src"
    src.mkdir()
    watched = tmp_path / "watched"
    watched.mkdir()
    img = _image(5, 64, 64)
    if suffix == ".sxm":
        ref = write_sxm(
            src / "f.sxm", img, pixel_size_nm=(1, 1), start=datetime.now(), line_time_s=0.01
        )
    else:
        ref = _tif(src / "f.tif", 5)
        img = _image(5)
    inst = FolderInstrument(tmp_path / "watched", poll_s=POLL_S, read_attempts=100)
    async with inst:
        writer = _slow_writer(ref.read_bytes(), watched / ref.name, chunks=6, pause_s=pause_s)
        try:
            (frame,) = await _drain(inst, until=1)
        finally:
            await asyncio.to_thread(writer.join)
        assert await inst.latest_frame() is frame  # nothing more
    np.testing.assert_allclose(frame.heights_nm, img, rtol=1e-6, atol=1e-5)
    if pause_s < POLL_S:
        assert inst.read_errors == 0
    assert inst.skipped == []


@pytest.mark.asyncio
async def test_a_file_that_never_reads_is_skipped_after_bounded_attempts(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, read_attempts=2)
    async with inst:
        (tmp_path / "broken.sxm").write_bytes(b":NANONIS_VERSION:\n2\n")
        _tif(tmp_path / "good.tif", 0)
        await _drain(inst, until=1)
        await asyncio.sleep(6 * POLL_S)
        for _ in range(5):
            await inst.latest_frame()
            await asyncio.sleep(POLL_S)
    assert inst.delivered == ["good.tif"]
    assert [name for name, _ in inst.skipped] == ["broken.sxm"]
    assert "truncated" in inst.skipped[0][1]
    assert inst.read_errors == 2


@pytest.mark.asyncio
async def test_a_multi_frame_file_gives_every_frame(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, line_time_s=0.01)
    async with inst:
        stack = np.stack([_image(i) for i in range(3)])
        np.save(tmp_path / "stack.npy", stack)  # no calibration: reported, skipped
        import tifffile

        tifffile.imwrite(
            tmp_path / "stack.tif",
            stack.astype(np.float32),
            imagej=True,
            resolution=(1.0, 1.0),
            metadata={"unit": "nm"},
        )
        frames = await _drain(inst, until=3)
    assert inst.delivered == ["stack.tif:0", "stack.tif:1", "stack.tif:2"]
    for i, f in enumerate(frames):
        np.testing.assert_allclose(f.heights_nm, stack[i].astype(np.float32))


@pytest.mark.asyncio
async def test_sensor_log_gives_the_last_complete_row(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path, poll_s=POLL_S, origin_s=1_700_000_000.0)
    log = tmp_path / "sensors.csv"
    async with inst:
        assert (await inst.read_channels()).values == {}
        log.write_text("unix_s,temperature_c,humidity_pct\n1700000010,21.5,40\n1700000011,21.6,4")
        sample = await inst.read_channels()
        assert sample.t_s == pytest.approx(10.0)
        assert dict(sample.values) == {"temperature_c": 21.5, "humidity_pct": 40.0}
        with log.open("a") as f:
            f.write("1\n# a comment\n1700000012,bad,1\n")
        sample = await inst.read_channels()
        assert sample.t_s == pytest.approx(11.0)
        assert dict(sample.values) == {"temperature_c": 21.6, "humidity_pct": 41.0}
        iso = datetime.fromtimestamp(1_700_000_020.5).isoformat()
        log.write_text(f"time,temperature_c\n{iso},22.0\n")  # rewritten, shorter
        sample = await inst.read_channels()
        assert sample.t_s == pytest.approx(20.5)
        assert dict(sample.values) == {"temperature_c": 22.0}


@pytest.mark.asyncio
async def test_offsets_cannot_be_set_and_there_is_no_event_log(tmp_path: Path) -> None:
    inst = FolderInstrument(tmp_path)
    async with inst:
        with pytest.raises(OffsetNotSupportedError, match="cannot move the scan offset"):
            await inst.set_offset(1.0, 2.0)
        assert await inst.get_offset() == (0.0, 0.0)
        assert await inst.events(0) == []
    assert issubclass(OffsetNotSupportedError, InstrumentError)


@pytest.mark.asyncio
async def test_missing_folder_is_a_connection_failure(tmp_path: Path) -> None:
    with pytest.raises(InstrumentDisconnected, match="no such directory"):
        await FolderInstrument(tmp_path / "absent").connect()


def test_folder_url_and_options_from_config(tmp_path: Path) -> None:
    inst = instrument_from_config(
        DriverConfig(
            transport=f"folder:{tmp_path}",
            folder_poll_s=0.5,
            folder_line_time_s=0.02,
            folder_channel="Z",
        )
    )
    assert isinstance(inst, FolderInstrument)
    assert (inst.path, inst.poll_s, inst.line_time_s, inst.channel) == (tmp_path, 0.5, 0.02, "Z")


@pytest.mark.parametrize(
    ("driver", "pattern"),
    [
        ({"transport": "folder:"}, "folder: needs a directory"),
        ({"folder_poll_s": 0}, r"driver\.folder_poll_s = 0.*>= 0.01"),
        ({"folder_line_time_s": -1.0}, r"driver\.folder_line_time_s"),
        ({"folder_sensor_file": "../x.csv"}, "file name inside the folder"),
        ({"folder_channel": ""}, r"driver\.folder_channel"),
    ],
)
def test_bad_folder_options_are_refused(driver: dict[str, object], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        parse_config({"driver": driver})


def test_closed_loop_with_a_folder_is_refused_at_check_time(tmp_path: Path) -> None:
    from afmdrift.service import check_config

    cfg = parse_config(
        {"driver": {"transport": f"folder:{tmp_path}"}, "service": {"closed_loop": True}}
    )
    with pytest.raises(ConfigError, match=r"closed_loop = true.*cannot move the scan offset"):
        check_config(cfg)
    open_loop = parse_config({"service": {"closed_loop": True}})
    with pytest.raises(ConfigError, match="folder of saved images"):
        check_config(open_loop, instrument_url=f"folder:{tmp_path}")

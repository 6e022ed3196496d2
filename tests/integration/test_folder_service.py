"""The daemon on a folder instrument while a writer saves simulator frames into it.

A writer thread saves simulator frames as Nanonis ``.sxm`` and ImageJ ``.tif``
files, the way vendor software does: some written in place in chunks with
pauses longer than the folder's scan period (so a stable partial file is
seen and must be refused by its reader), some written under a temporary name
and renamed. Every file must become exactly one recorded frame, in order,
with its full contents, and the drift it measures must follow the simulator's.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import running_service, service_config, small_scenario

from afmdrift.client import Subscriber
from afmdrift.drivers import FolderInstrument
from afmdrift.drivers.sim import SimulatedAFM
from afmdrift.io import load_image, write_sxm, write_tif
from afmdrift.records import Frame
from afmdrift.service import RunStore
from afmdrift.wire import FrameMsg

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]

N_FILES = 10
POLL_S = 0.05


def _sim_frames(n: int) -> list[Frame]:
    sim = SimulatedAFM(small_scenario(drift_nm_per_sqrt_s=0.3, frame_period_s=16.0))
    frames: list[Frame] = []
    t = 0.0
    while len(frames) < n:
        t += 16.0
        frames += sim.advance_to(t)
    return frames[:n]


def _save(frame: Frame, path: Path, start: datetime) -> Path:
    if path.suffix == ".sxm":
        return write_sxm(
            path,
            frame.heights_nm,
            pixel_size_nm=frame.pixel_size_nm,
            start=start,
            line_time_s=frame.line_time_s,
            direction=frame.direction,
        )
    return write_tif(
        path,
        frame.heights_nm,
        pixel_size_nm=frame.pixel_size_nm,
        start=start,
        line_time_s=frame.line_time_s,
        direction=frame.direction,
    )


def _writer(sources: list[Path], folder: Path, done: dict[str, float]) -> threading.Thread:
    def run() -> None:
        for k, src in enumerate(sources):
            data = src.read_bytes()
            if k % 2:  # in place, in 4 chunks, pausing longer than a folder scan
                dest = folder / src.name
                with dest.open("wb") as f:
                    for j in range(4):
                        f.write(data[j * len(data) // 4 : (j + 1) * len(data) // 4])
                        f.flush()
                        os.fsync(f.fileno())
                        if j < 3:
                            time.sleep(3 * POLL_S)
            else:  # under a temporary name, then renamed
                tmp = folder / f"{src.name}.tmp"
                tmp.write_bytes(data)
                time.sleep(2 * POLL_S)
                tmp.rename(folder / src.name)
            done[src.name] = time.time()
            with (folder / "sensors.csv").open("a") as log:
                log.write(f"{time.time():.3f},{21.0 + 0.1 * k:.2f}\n")
            time.sleep(0.3)

    return threading.Thread(target=run, daemon=True)


async def test_every_saved_file_becomes_one_full_frame(tmp_path: Path) -> None:
    src, folder = tmp_path / "src", tmp_path / "afm"
    src.mkdir()
    folder.mkdir()
    (folder / "sensors.csv").write_text("unix_s,temperature_c\n")
    frames = _sim_frames(N_FILES)
    # Header dates as the instrument wrote them: 16 s apart, ending before now.
    t0 = time.time() - 16.0 * (N_FILES + 2)
    sources = [
        _save(
            f,
            src / f"scan{k:03d}{'.sxm' if k % 3 else '.tif'}",
            datetime.fromtimestamp(t0 + f.t_start_s),
        )
        for k, f in enumerate(frames)
    ]
    ctx = zmq.asyncio.Context()
    done: dict[str, float] = {}
    msgs: list[FrameMsg] = []
    instrument = FolderInstrument(folder, poll_s=POLL_S, read_attempts=50)
    cfg = service_config(tmp_path / "run", frame_poll_interval_s=0.05)
    try:
        async with running_service(cfg, instrument, ctx) as service:
            sub = Subscriber(service.pub_endpoint, ctx=ctx)
            writer = _writer(sources, folder, done)
            try:
                await asyncio.sleep(0.3)  # the subscription is up
                writer.start()
                async with asyncio.timeout(90):
                    while len(msgs) < N_FILES:
                        msg = await sub.recv()
                        if isinstance(msg, FrameMsg):
                            msgs.append(msg)
            finally:
                sub.close()
                await asyncio.to_thread(writer.join, 30)
            stored = RunStore(tmp_path / "run").frames()
    finally:
        ctx.term()

    names = [s.name for s in sources]
    assert instrument.delivered == names  # every file, once, in order
    assert instrument.skipped == []
    assert [m.instrument_frame for m in msgs] == list(range(N_FILES))
    assert [r.instrument_frame for r in stored] == list(range(N_FILES))
    # the frames are the files' full contents, timed from their headers
    for r, f, p in zip(stored, frames, sources, strict=True):
        assert (r.rows, r.cols) == f.shape
        assert r.t_end_s - r.t_start_s == pytest.approx(f.t_end_s - f.t_start_s, abs=1e-6)
        assert load_image(p).shape == f.shape
    ends = np.array([r.t_end_s for r in stored])
    assert np.diff(ends) == pytest.approx(16.0, abs=1.01)  # .sxm dates have 1 s resolution
    # registration worked on every frame after the reference
    assert stored[0].reason == "reference"
    assert all(r.fed_model for r in stored[1:]), [r.reason for r in stored]
    # each frame was published within 1 s of its file being complete
    for m, name in zip(msgs, names, strict=True):
        assert 0 < m.wall_s - done[name] < 1.0, (name, m.wall_s - done[name])

"""Benchmark of the folder instrument: 200 files saved into a folder while the daemon runs.

A writer thread saves 200 image files into a folder the way vendor software
does, with pauses: simulator frames as Nanonis ``.sxm`` and ImageJ ``.tif``
(256×256 px, timed in their headers), and copies of the real NanoScope and
Gwyddion files of ``../shared/data/real`` (when present; timed by their mtime,
their header dates being years old). Half the files are written in place in
four chunks with pauses longer than the folder's scan period (a stable partial
file is seen and must be refused by its reader), half under a ``.tmp`` name
and renamed. The HS-AFM ``.asd`` movie is left out: 32 frames in one file
cannot each be processed within 1 s of that file appearing.

The daemon (:class:`~afmdrift.service.DriftService` with default registration
and model settings, ``frame_poll_interval_s = 0.05``, ``folder_poll_s = 0.2``)
runs in this process; a subscriber counts the ``frame`` and ``model`` messages.

Prints, per file: missed (never a frame), partial reads (a frame whose heights
differ from the complete file's), and the latency from the file being complete
(the writer's last byte or rename) to the frame's ``frame`` message being
published (its ``wall_s``) and to its ``model`` message arriving here, as
p50 / p99 / max.

Usage: ``python benchmarks/bench_folder.py [--files 200]`` (about 3 minutes).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import zmq.asyncio

from afmdrift.client import Subscriber
from afmdrift.config import parse_config
from afmdrift.drivers import FolderInstrument, Frame
from afmdrift.drivers.sim import SimulatedAFM, parse_scenario
from afmdrift.io import load_stack, write_sxm, write_tif
from afmdrift.service import DriftService
from afmdrift.wire import FrameMsg, ModelMsg

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
REAL_FILES = ("nanoscope3a_15um.002", "nanoscope3a_15um.004")
POLL_S = 0.2
FRAME_S = 4.0  # simulator frame: 256 lines at 64 Hz


def _digest(a: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(a, dtype=np.float64).tobytes()).hexdigest()


class RecordingFolder(FolderInstrument):
    """Keeps a digest of every frame handed out, to find partial reads."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.digests: list[str] = []

    async def latest_frame(self) -> Frame | None:
        n = len(self.delivered)
        frame = await super().latest_frame()
        if len(self.delivered) > n and frame is not None:
            self.digests.append(_digest(frame.heights_nm))
        return frame


def sim_sources(n: int, out: Path) -> list[Path]:
    scenario = parse_scenario(
        {
            "name": "bench-folder",
            "seed": 5,
            "duration_s": 86400.0,
            "scan": {
                "pixels": [256, 256],
                "size_nm": [1024.0, 1024.0],
                "line_rate_hz": 64.0,
                "frame_period_s": FRAME_S,
                "directions": "up",
            },
            "sample": {"kind": "gold_on_mica", "grid_nm": 2.0, "map_px": 1024},
            "physics": {"random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": [0.2, 0.2]}},
        },
        source="bench-folder",
    )
    sim = SimulatedAFM(scenario)
    frames: list[Frame] = []
    t = 0.0
    while len(frames) < n:
        t += FRAME_S
        frames += sim.advance_to(t)
    paths = []
    for k, f in enumerate(frames[:n]):
        writer = write_sxm if k % 2 == 0 else write_tif
        # Placeholder date; the writer rewrites it to "now" when it saves the file.
        paths.append(
            writer(
                out / f"sim{k:03d}{'.sxm' if k % 2 == 0 else '.tif'}",
                f.heights_nm,
                pixel_size_nm=f.pixel_size_nm,
                start=datetime.now(),
                line_time_s=f.line_time_s,
            )
        )
    return paths


def plan(n_files: int, staging: Path) -> list[tuple[str, Path | None, int]]:
    """(name in the folder, real file or None, simulator frame index) per file."""
    real = [REAL / name for name in REAL_FILES if (REAL / name).is_file()]
    out: list[tuple[str, Path | None, int]] = []
    sim_k = 0
    for i in range(n_files):
        if real and i % 4 == 3:
            src = real[(i // 4) % len(real)]
            out.append((f"real{i:03d}{src.suffix}", src, -1))
        else:
            out.append(("", None, sim_k))
            sim_k += 1
    return out


def writer_thread(
    n: int,
    item: Callable[[int], tuple[str, bytes]],
    folder: Path,
    done: list[float],
    pause_s: float,
) -> threading.Thread:
    def run() -> None:
        for k in range(n):
            name, data = item(k)
            dest = folder / name
            if k % 2:
                with dest.open("wb") as f:
                    for j in range(4):
                        f.write(data[j * len(data) // 4 : (j + 1) * len(data) // 4])
                        f.flush()
                        os.fsync(f.fileno())
                        if j < 3:
                            time.sleep(1.5 * POLL_S)
            else:
                tmp = folder / f"{name}.tmp"
                tmp.write_bytes(data)
                tmp.rename(dest)
            done.append(time.time())
            with (folder / "sensors.csv").open("a") as log:
                log.write(f"{time.time():.3f},{21.0 + 0.001 * k:.3f}\n")
            time.sleep(pause_s)

    return threading.Thread(target=run, daemon=True)


def prepare(n_files: int, staging: Path) -> tuple[list[tuple[str, bytes]], list[str]]:
    """File names and bytes in writing order, and the digest of each file's frame."""
    layout = plan(n_files, staging)
    sims = sim_sources(sum(1 for _, r, _ in layout if r is None), staging)
    items: list[tuple[str, bytes]] = []
    digests: list[str] = []
    for name, real, k in layout:
        if real is None:
            src = sims[k]
            items.append((src.name, b""))  # bytes made at write time (fresh header date)
        else:
            items.append((name, real.read_bytes()))
            copy = staging / name
            shutil.copyfile(real, copy)
            src = copy
        (image,) = load_stack(src)
        digests.append(_digest(image.heights_nm))
    return items, digests


def fresh_sim_bytes(src: Path, staging: Path) -> bytes:
    """The simulator frame saved again with its scan ending now (as an AFM would)."""
    (image,) = load_stack(src)
    start = datetime.fromtimestamp(time.time() - image.shape[0] / 64.0)
    out = staging / f"fresh{src.suffix}"
    writer = write_sxm if src.suffix == ".sxm" else write_tif
    writer(
        out,
        image.heights_nm,
        pixel_size_nm=image.pixel_size_nm,
        start=start,
        line_time_s=1 / 64.0,
    )
    return out.read_bytes()


def setup(n_files: int, staging: Path, folder: Path) -> tuple[list[tuple[str, bytes]], list[str]]:
    staging.mkdir()
    folder.mkdir()
    (folder / "sensors.csv").write_text("unix_s,temperature_c\n")
    return prepare(n_files, staging)


async def main(n_files: int, pause_s: float) -> None:
    logging.basicConfig(level=logging.ERROR)
    with tempfile.TemporaryDirectory() as tmp:
        staging, folder, run_dir = Path(tmp, "staging"), Path(tmp, "afm"), Path(tmp, "run")
        items, digests = setup(n_files, staging, folder)

        def item(k: int) -> tuple[str, bytes]:
            # Simulator files are saved with a header date of "now", as an AFM would.
            name, data = items[k]
            return name, data or fresh_sim_bytes(staging / name, staging)

        cfg = parse_config(
            {
                "service": {
                    "pub_endpoint": "tcp://127.0.0.1:*",
                    "control_endpoint": "tcp://127.0.0.1:*",
                    "run_dir": str(run_dir),
                    "frame_poll_interval_s": 0.05,
                    "channel_poll_interval_s": 1.0,
                },
                "model": {"predictor": "constant_velocity"},
            }
        )
        instrument = RecordingFolder(folder, poll_s=POLL_S, read_attempts=20)
        ctx = zmq.asyncio.Context()
        done: list[float] = []
        frame_wall: dict[int, float] = {}  # instrument frame -> frame message wall_s
        instrument_of: dict[int, int] = {}  # session frame -> instrument frame
        model_rx: dict[int, float] = {}  # session frame -> model message received
        service = DriftService(config=cfg, instrument=instrument, ctx=ctx)
        task = asyncio.create_task(service.run())
        await service.ready.wait()
        sub = Subscriber(service.pub_endpoint, ctx=ctx)
        writer = writer_thread(len(items), item, folder, done, pause_s)
        t_start = time.time()
        try:
            await asyncio.sleep(0.5)
            writer.start()
            deadline = time.time() + n_files * (pause_s + 2.0) + 30
            while len(frame_wall) < len(instrument.delivered) or (
                set(name for name, _ in items) - set(instrument.delivered)
            ):
                if time.time() > deadline:
                    break
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(1.0):
                        msg = await sub.recv()
                        if isinstance(msg, FrameMsg):
                            frame_wall[msg.instrument_frame] = msg.wall_s
                            instrument_of[msg.frame] = msg.instrument_frame
                        elif isinstance(msg, ModelMsg):
                            model_rx[msg.frame] = time.time()
            await asyncio.sleep(1.0)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.5):
                    while True:
                        msg = await sub.recv()
                        if isinstance(msg, ModelMsg):
                            model_rx[msg.frame] = time.time()
        finally:
            sub.close()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            ctx.term()
            await asyncio.to_thread(writer.join, 30)
        elapsed = time.time() - t_start

    names = [name for name, _ in items]
    delivered = instrument.delivered
    missed = [n for n in names if n not in delivered]
    expected = dict(zip(names, digests, strict=True))
    partial = [n for n, d in zip(delivered, instrument.digests, strict=True) if expected[n] != d]
    repeated = sorted({n for n in delivered if delivered.count(n) > 1})
    index = {n: i for i, n in enumerate(delivered)}
    lat_frame = np.array(
        [frame_wall[index[n]] - done[k] for k, n in enumerate(names) if index.get(n) in frame_wall]
    )
    model_at = {instrument_of[f]: t for f, t in model_rx.items() if f in instrument_of}
    lat_model = np.array(
        [model_at[index[n]] - done[k] for k, n in enumerate(names) if index.get(n) in model_at]
    )
    n_real = sum(1 for n in names if n.startswith("real"))
    print(f"files written: {len(names)} ({n_real} real copies, {len(names) - n_real} simulator)")
    print(
        f"wall time: {elapsed:.0f} s; read errors (partial files refused): {instrument.read_errors}"
    )
    print(f"frames handed out: {len(delivered)}; missed: {len(missed)} {missed[:5]}")
    print(f"partial reads: {len(partial)} {partial[:5]}; skipped: {instrument.skipped}")
    print(f"files handed out more than once: {len(repeated)} {repeated[:5]}")
    for label, lat in (
        ("complete -> frame published", lat_frame),
        ("complete -> model received", lat_model),
    ):
        if lat.size:
            print(
                f"{label}: n={lat.size} p50 {np.percentile(lat, 50) * 1e3:.0f} ms, "
                f"p99 {np.percentile(lat, 99) * 1e3:.0f} ms, max {lat.max() * 1e3:.0f} ms, "
                f"over 1 s: {int((lat > 1.0).sum())}"
            )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--files", type=int, default=200)
    parser.add_argument("--pause-s", type=float, default=0.5, help="pause after each file")
    args = parser.parse_args()
    asyncio.run(main(args.files, args.pause_s))

"""Benchmark of the drift service: latency, offset-stream jitter, idle CPU.

Runs the simulator (``afmdrift sim serve``) and the daemon (``afmdrift run``)
as separate processes on loopback TCP, subscribes from this process, and
prints:

* latency from frame-ready to model-published, p50 and p99, two ways:
  inside the daemon (frame seen by the poll → ``frame`` message sent, the
  ``latency_s`` field) and end to end (instrument finished the frame, mapped
  to wall time through the published clock → ``model`` message received here,
  which includes the frame poll interval);
* jitter of the offset stream at 100 Hz and at 1 kHz while 512×512 frames are
  being processed (spacing of the publisher's ``wall_s`` stamps);
* CPU use of the daemon process while idle between frames (% of one core).

Frames are 512×512 px with the default registration and model configuration
(the paper's setting); the simulator runs 128× faster than real time so a
256 s frame period takes 2 s.

Usage: ``python benchmarks/bench_service.py`` (about 3 minutes on 2 cores).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import zmq.asyncio

from afmdrift.client import Subscriber
from afmdrift.wire import FrameMsg, ModelMsg, OffsetMsg

REPO = Path(__file__).resolve().parent.parent
SCENARIO = """
name = "bench-service"
seed = 11
duration_s = 864000.0
[scan]
pixels = [512, 512]
size_nm = [2048.0, 2048.0]
line_rate_hz = 4.0
frame_period_s = 256.0
directions = "up"
[sample]
kind = "graphite"
grid_nm = 4.0
map_px = 2048
[physics.warmup]
enabled = true
amplitude_nm = [600.0, -400.0]
tau_s = 14400.0
[physics.random_walk]
enabled = true
sigma_nm_per_sqrt_s = [0.1, 0.1]
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Rig:
    """Simulator and daemon processes plus a subscriber in this process."""

    def __init__(self, tmp: Path, *, speed: float, rate_hz: float, name: str) -> None:
        self.tmp = tmp
        self.speed = speed
        self.rate_hz = rate_hz
        self.name = name
        self.pub = f"tcp://127.0.0.1:{_port()}"
        self.sim: subprocess.Popen[str] | None = None
        self.daemon: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> _Rig:
        scenario = self.tmp / "scenario.toml"
        scenario.write_text(SCENARIO, encoding="utf-8")
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "afmdrift", "sim", "serve", "--port", "0",
             "--scenario", str(scenario), "--speed", str(self.speed)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        assert self.sim.stdout is not None
        port = int(self.sim.stdout.readline())
        cfg = self.tmp / f"{self.name}.toml"
        cfg.write_text(
            f'[service]\nrun_dir = "{self.tmp / self.name}"\npub_endpoint = "{self.pub}"\n'
            f'control_endpoint = "tcp://127.0.0.1:{_port()}"\noffset_rate_hz = {self.rate_hz}\n'
            "frame_poll_interval_s = 0.05\n",
            encoding="utf-8",
        )
        self.daemon = subprocess.Popen(
            [sys.executable, "-m", "afmdrift", "run", "--config", str(cfg),
             "--instrument", f"socket://127.0.0.1:{port}"],
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        return self

    def __exit__(self, *exc: object) -> None:
        for p in (self.daemon, self.sim):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        if self.sim is not None and self.sim.stdout is not None:
            self.sim.stdout.close()


async def _collect(rig: _Rig, ctx: zmq.asyncio.Context, *, frames: int) -> dict[str, list[float]]:
    sub = Subscriber(rig.pub, ctx=ctx)
    out: dict[str, list[float]] = {"internal": [], "e2e": [], "offset_wall": []}
    seen = 0
    try:
        async with asyncio.timeout(600):
            while seen < frames:
                msg = await sub.recv()
                now = time.time()
                if isinstance(msg, OffsetMsg):
                    out["offset_wall"].append(msg.wall_s)
                elif isinstance(msg, FrameMsg):
                    seen += 1
                    if seen > 2:  # skip start-up frames (imports, first fits)
                        out["internal"].append(msg.latency_s)
                elif isinstance(msg, ModelMsg) and seen >= 2:
                    c = msg.clock
                    t_end = msg.t_s + 64.0  # mid-scan + half the 128 s scan
                    ready_wall = c.wall_s + (t_end - c.instrument_s) / c.rate
                    out["e2e"].append(now - ready_wall)
    finally:
        sub.close()
    return out


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def _jitter(walls: list[float], rate_hz: float) -> str:
    d = np.diff(np.asarray(walls))
    err = np.abs(d - 1.0 / rate_hz) * 1e3
    return (
        f"mean period {1e3 * d.mean():.3f} ms (target {1e3 / rate_hz:.3f}), "
        f"|error| p50 {np.percentile(err, 50):.3f} ms, p99 {np.percentile(err, 99):.3f} ms, "
        f"max {err.max():.3f} ms, std {1e3 * d.std():.3f} ms over {d.size} intervals"
    )


async def _idle_cpu(rig: _Rig, ctx: zmq.asyncio.Context, window_s: float) -> float:
    assert rig.daemon is not None
    sub = Subscriber(rig.pub, topics=("frame",), ctx=ctx)
    try:
        await sub.recv(timeout_s=120)  # the first frame (256 s at speed 1 is long: wait one)
    finally:
        sub.close()
    await asyncio.sleep(2.0)
    proc = psutil.Process(rig.daemon.pid)
    c0, t0 = proc.cpu_times(), time.monotonic()
    await asyncio.sleep(window_s)
    c1, t1 = proc.cpu_times(), time.monotonic()
    return 100.0 * ((c1.user - c0.user) + (c1.system - c0.system)) / (t1 - t0)


async def main() -> None:
    ctx = zmq.asyncio.Context()
    print("bench_service: simulator + daemon processes on loopback TCP, 512x512 frames")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for rate, frames in ((100.0, 22), (1000.0, 12)):
                with _Rig(Path(tmp), speed=128.0, rate_hz=rate, name=f"r{int(rate)}") as rig:
                    res = await _collect(rig, ctx, frames=frames)
                print(f"offset stream at {rate:g} Hz while processing frames: "
                      f"{_jitter(res['offset_wall'], rate)}")  # fmt: skip
                print(
                    f"  latency frame seen -> frame/model published (in daemon): "
                    f"p50 {1e3 * _pct(res['internal'], 50):.1f} ms, "
                    f"p99 {1e3 * _pct(res['internal'], 99):.1f} ms (n={len(res['internal'])})"
                )
                print(
                    f"  latency frame completed -> model received (end to end, incl. 50 ms "
                    f"poll): p50 {1e3 * _pct(res['e2e'], 50):.1f} ms, "
                    f"p99 {1e3 * _pct(res['e2e'], 99):.1f} ms (n={len(res['e2e'])})"
                )
            for rate in (100.0, 1000.0):
                with _Rig(Path(tmp), speed=20.0, rate_hz=rate, name=f"idle{int(rate)}") as rig:
                    cpu = await _idle_cpu(rig, ctx, window_s=8.0)
                print(f"idle CPU between frames, offset stream at {rate:g} Hz: "
                      f"{cpu:.1f} % of one core")  # fmt: skip
        print(f"(machine: {psutil.cpu_count()} cores; load is shared with other processes)")
    finally:
        ctx.term()


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())

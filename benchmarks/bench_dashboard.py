"""Benchmark of the dashboard: frame-to-page latency, CPU and memory over a long run.

Runs the simulator (``afmdrift sim serve``), the daemon (``afmdrift run``, offset
stream at 1 kHz, frames archived so the dashboard re-measures each one) and the
dashboard (``afmdrift dashboard --run-dir RUN --pub EP``) as separate processes
on loopback, opens the page in headless Chromium, and prints:

* latency from a ``frame`` message's publication (its ``wall_s``) to its point
  drawn on the page (the page's own clock after Plotly finished drawing),
  p50 and p99, measured in the browser;
* CPU of the dashboard process (% of one core, mean and max over 10 s windows)
  and its resident memory (after the first page load, after the first minute,
  at the end, maximum);
* offset samples the dashboard received against those the daemon published;
* the load average at start and end (the machine may be shared).

The instrument runs ``--hours`` (default 1) of simulated time ``--speed`` (default
12) times faster than real time: 128×128 px frames every 60 s, so one hour takes
5 minutes of wall time with a frame every 5 s.

Usage: ``python benchmarks/bench_dashboard.py [--hours 1] [--speed 12]``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import psutil

from afmdrift.dashboard._chromium import HeadlessChromium

REPO = Path(__file__).resolve().parent.parent
SCENARIO = """
name = "bench-dashboard"
seed = 5
duration_s = 864000.0
[scan]
pixels = [128, 128]
size_nm = [512.0, 512.0]
line_rate_hz = 4.0
frame_period_s = 60.0
directions = "up"
[sample]
kind = "gold_on_mica"
grid_nm = 2.0
map_px = 1024
roughness_nm = 0.3
[sample.gold]
density_per_um2 = 80.0
[physics.warmup]
enabled = true
amplitude_nm = [40.0, -30.0]
tau_s = 1800.0
[physics.random_walk]
enabled = true
sigma_nm_per_sqrt_s = [0.02, 0.02]
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "afmdrift", *args], cwd=REPO, stdout=fh, stderr=subprocess.STDOUT
        )


def _wait_for_file(path: Path, timeout_s: float) -> None:
    """Return once ``path`` exists (the daemon creates its store at start-up)."""
    deadline = time.monotonic() + timeout_s
    while not path.is_file():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} did not appear within {timeout_s:g} s")
        time.sleep(0.2)


async def _state(http: aiohttp.ClientSession, url: str) -> dict[str, Any]:
    async with http.get(url + "state.json") as resp:
        doc: dict[str, Any] = await resp.json()
        return doc


async def bench(hours: float, speed: float, offset_rate_hz: float) -> None:
    load0 = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="afmdrift-bench-dashboard-"))
    scenario = tmp / "scenario.toml"
    scenario.write_text(SCENARIO, encoding="utf-8")
    pub = f"tcp://127.0.0.1:{_free_port()}"
    run_dir = tmp / "run"
    (tmp / "daemon.toml").write_text(
        f"""[service]
pub_endpoint = "{pub}"
control_endpoint = "tcp://127.0.0.1:{_free_port()}"
run_dir = "{run_dir}"
archive_frames = true
offset_rate_hz = {offset_rate_hz}
frame_poll_interval_s = 0.05
clock_sync_interval_s = 0.2
heartbeat_interval_s = 1.0
[registration]
block_size = 32
extended_size = 64
""",
        encoding="utf-8",
    )
    sim_port = _free_port()
    dash_port = _free_port()
    procs = [
        _spawn(
            [
                "sim",
                "serve",
                "--port",
                str(sim_port),
                "--scenario",
                str(scenario),
                "--speed",
                f"{speed:g}",
            ],
            tmp / "sim.log",
        )
    ]
    try:
        await asyncio.sleep(1.5)
        procs.append(
            _spawn(
                [
                    "run",
                    "--config",
                    str(tmp / "daemon.toml"),
                    "--instrument",
                    f"socket://127.0.0.1:{sim_port}",
                ],
                tmp / "daemon.log",
            )
        )
        await asyncio.to_thread(_wait_for_file, run_dir / "run.sqlite", 60.0)
        dash = _spawn(
            ["dashboard", "--run-dir", str(run_dir), "--pub", pub, "--port", str(dash_port)],
            tmp / "dashboard.log",
        )
        procs.append(dash)
        url = f"http://127.0.0.1:{dash_port}/"
        proc = psutil.Process(dash.pid)
        async with aiohttp.ClientSession() as http, HeadlessChromium() as browser:
            async with asyncio.timeout(60):
                while True:
                    try:
                        await _state(http, url)
                        break
                    except aiohttp.ClientError:
                        await asyncio.sleep(0.2)
            await browser.goto(url)
            await browser.wait_for("window.afmdriftDashboard.snapshots > 0", timeout_s=60)
            proc.cpu_percent(None)
            rss0 = proc.memory_info().rss
            cpu: list[float] = []
            rss: list[int] = [rss0]
            started = time.monotonic()
            offsets0 = (await _state(http, url))["link"]["by_topic"]["offset"]
            end_t_s = hours * 3600.0
            budget_s = 1.5 * end_t_s / speed + 120.0
            t_s = 0.0
            while t_s < end_t_s and time.monotonic() - started < budget_s:
                await asyncio.sleep(10.0)
                cpu.append(proc.cpu_percent(None))
                rss.append(proc.memory_info().rss)
                st = await _state(http, url)
                status = st.get("status") or {}
                t_s = float(status.get("t_s") or 0.0)
            wall_s = time.monotonic() - started
            st = await _state(http, url)
            offsets = st["link"]["by_topic"]["offset"] - offsets0
            latencies = np.asarray(
                await browser.evaluate("window.afmdriftDashboard.latenciesMs"), dtype=float
            )
            errors = list(browser.errors)
        load1 = os.getloadavg()
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(tmp, ignore_errors=True)
    print(
        f"dashboard benchmark: {t_s / 3600:.2f} h of instrument time in {wall_s:.0f} s "
        f"(speed {speed:g}), offsets at {offset_rate_hz:g} Hz, 128x128 px frames every 60 s"
    )
    if latencies.size:
        p50, p99 = np.percentile(latencies, [50, 99])
        print(
            f"frame message -> point on the page: p50 {p50:.0f} ms, p99 {p99:.0f} ms, "
            f"max {latencies.max():.0f} ms over {latencies.size} frames"
        )
    else:
        print("frame message -> point on the page: no frame reached the page")
    print(
        f"dashboard CPU: mean {np.mean(cpu):.1f} %, max {np.max(cpu):.1f} % of one core "
        f"(10 s windows, {len(cpu)} windows)"
    )
    print(
        f"dashboard RSS: {rss0 / 2**20:.0f} MiB after the first page load, "
        f"{rss[min(6, len(rss) - 1)] / 2**20:.0f} MiB after the first minute (the first "
        f"re-measured frame loads the registration engine), {rss[-1] / 2**20:.0f} MiB at the "
        f"end, max {max(rss) / 2**20:.0f} MiB"
    )
    print(
        f"offset samples received by the dashboard: {offsets} "
        f"({offsets / wall_s:.0f} per s; published {offset_rate_hz:g} per s)"
    )
    print(f"page console errors: {len(errors)}")
    print(
        f"load average (1, 5, 15 min): start {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
        f"end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f} (shared machine, {os.cpu_count()} cores)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hours", type=float, default=1.0, help="instrument hours (default 1)")
    parser.add_argument("--speed", type=float, default=12.0, help="acceleration (default 12)")
    parser.add_argument(
        "--offset-rate-hz", type=float, default=1000.0, help="daemon offset rate (default 1000)"
    )
    args = parser.parse_args()
    asyncio.run(bench(args.hours, args.speed, args.offset_rate_hz))


if __name__ == "__main__":
    main()

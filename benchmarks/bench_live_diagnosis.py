"""Benchmark of the live diagnosis: does it cost the frames anything, and does it cry wolf?

Two parts, chosen on the command line (default: both):

``latency``
    The simulator (``config/scenarios/hidden/humidity.toml``: 128² px frames
    every 300 s, a humidity cycle the default model lacks) paced at a stated
    speed-up (``--speed``, default 150: a frame every 2 wall seconds) on
    loopback TCP, the daemon (in this process, the production driver, the
    default physics model) run twice in one invocation: live diagnosis off
    (``diagnose_every_frames = 0``), then on (every 10 frames). For each:
    frames lost (dropped by the acquisition, failed, or missing from the run
    store's instrument frame numbers; must be 0), the frame-to-offset latency
    (frame seen → its model published, the daemon's own figure) at the 50th
    and 95th percentile, and the diagnoses made. Target: p95 on within 5 % of
    off.
``control``
    Nothing missing: the control scenario (every effect of the instrument is
    in the default model) run long enough for at least ``--looks`` (default
    50) live diagnoses of one run, a diagnosis every 2 frames; prints how
    many of them called any candidate significant (target: none; the looks
    are tested at their share of alpha, docs/diagnostics.md).

Usage: ``python benchmarks/bench_live_diagnosis.py [latency|control|both]``
(the latency part about 5 minutes, the control part about 15 on 2 cores).
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import os
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq.asyncio

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))

from service_sim import driver, running_service, service_config, sim_server  # noqa: E402

from afmdrift.client import Subscriber  # noqa: E402
from afmdrift.config import read_toml  # noqa: E402
from afmdrift.drivers.sim import load_scenario, parse_scenario  # noqa: E402
from afmdrift.wire import DiagnosisMsg, FrameMsg  # noqa: E402

HIDDEN = REPO / "config" / "scenarios" / "hidden"
SMALL_FRAMES = {"block_size": 32, "extended_size": 96}


def _stored_instrument_frames(run_dir: Path) -> list[int]:
    with sqlite3.connect(f"file:{run_dir / 'run.sqlite'}?mode=ro", uri=True) as db:
        return [int(r[0]) for r in db.execute("SELECT instrument_frame FROM frames ORDER BY seq")]


async def _one_run(
    scenario: Any, run_dir: Path, *, speed: float, frames: int, every: int, looks: int = 0
) -> dict[str, Any]:
    """The daemon on the simulator for ``frames`` frames, or until ``looks``
    diagnoses gave a result; its figures."""
    ctx = zmq.asyncio.Context()
    diagnoses: list[DiagnosisMsg] = []
    try:
        async with sim_server(scenario, speed=speed) as (_, url):
            cfg = service_config(
                run_dir, model={}, registration=SMALL_FRAMES, diagnose_every_frames=every
            )
            async with running_service(cfg, driver(url), ctx) as service:
                sub = Subscriber(service.pub_endpoint, ctx=ctx, topics=["frame", "diagnosis"])
                try:
                    async with asyncio.timeout(frames * 300.0 / speed * 3 + 120):
                        last = -1
                        while last < frames - 1 if looks == 0 else len(diagnoses) < looks:
                            msg = await sub.recv()
                            if isinstance(msg, FrameMsg):
                                last = msg.frame
                            elif isinstance(msg, DiagnosisMsg):
                                diagnoses.append(msg)
                finally:
                    sub.close()
                lat = np.array(list(service.latencies_s)[1:])  # the first frame compiles
                dropped = service.frames_dropped
                failed = service.publishing.faults.frames_failed
                ran = service.diagnosis.looks
                diag_failed = service.diagnosis.failed
                skipped = service.diagnosis.skipped
    finally:
        ctx.term()
    stored = _stored_instrument_frames(run_dir)
    gaps = sum(b - a - 1 for a, b in itertools.pairwise(stored) if b > a + 1)
    twice = len(stored) - len(set(stored))
    return {
        "frames": len(stored),
        "lost": dropped + failed + gaps,
        "twice": twice,
        "p50_ms": float(np.percentile(lat, 50) * 1e3),
        "p95_ms": float(np.percentile(lat, 95) * 1e3),
        "diagnoses": ran,
        "diagnoses_failed": diag_failed,
        "skipped": skipped,
        "diagnosis_s": [round(m.duration_s, 1) for m in diagnoses],
        "significant": [
            m.look
            for m in diagnoses
            if any(c.get("significant") for c in m.diagnosis.get("candidates", []))
        ],
    }


async def latency(speed: float, frames: int) -> None:
    scenario = load_scenario(HIDDEN / "humidity.toml")
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        off = await _one_run(scenario, Path(tmp) / "off", speed=speed, frames=frames, every=0)
        on = await _one_run(scenario, Path(tmp) / "on", speed=speed, frames=frames, every=10)
    print(f"latency: humidity scenario, speed-up {speed:g} ({300.0 / speed:.1f} s per frame), "
          f"{frames} frames each, load after {os.getloadavg()}")  # fmt: skip
    for name, r in (("off", off), ("on", on)):
        print(
            f"  diagnosis {name:3s}: frames {r['frames']}, lost {r['lost']}, twice {r['twice']}, "
            f"latency p50 {r['p50_ms']:.1f} ms p95 {r['p95_ms']:.1f} ms, diagnoses "
            f"{r['diagnoses']} (failed {r['diagnoses_failed']}, skipped {r['skipped']}, "
            f"durations {r['diagnosis_s']} s)"
        )
    print(f"  p95 on / off: {on['p95_ms'] / off['p95_ms']:.3f} (target <= 1.05)")


async def control(speed: float, looks: int) -> None:
    data = read_toml(HIDDEN / "control.toml", what="scenario")
    every = 2
    frames = 4 * looks * every  # a bound: a diagnosis requested while one runs is skipped
    data["duration_s"] = max(float(data["duration_s"]), (frames + 5) * 300.0)
    scenario = parse_scenario(data, source="control, lengthened")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-live-control-") as tmp:
        r = await _one_run(
            scenario, Path(tmp) / "run", speed=speed, frames=frames, every=every, looks=looks
        )
    took_s = time.perf_counter() - t0
    print(f"control: control scenario, speed-up {speed:g}, {r['frames']} frames, a diagnosis "
          f"every {every} frames, {took_s:.0f} s, load {os.getloadavg()}")  # fmt: skip
    print(f"  live diagnoses with a result: {r['diagnoses']} (failed {r['diagnoses_failed']}, "
          f"skipped while one ran {r['skipped']})")  # fmt: skip
    print(f"  diagnoses calling a candidate significant: {len(r['significant'])} "
          f"(looks {r['significant']}); frames lost {r['lost']}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", nargs="?", default="both", choices=["latency", "control", "both"])
    ap.add_argument("--speed", type=float, default=150.0, help="simulator speed-up (latency)")
    ap.add_argument("--frames", type=int, default=60, help="frames per latency run")
    ap.add_argument("--looks", type=int, default=50, help="live diagnoses wanted (control)")
    ap.add_argument("--control-speed", type=float, default=30.0, help="speed-up (control)")
    args = ap.parse_args()
    if args.part in ("latency", "both"):
        asyncio.run(latency(args.speed, args.frames))
    if args.part in ("control", "both"):
        asyncio.run(control(args.control_speed, args.looks))


if __name__ == "__main__":
    main()

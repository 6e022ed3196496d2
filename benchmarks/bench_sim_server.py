"""An 8 h session over the wire: the simulator's server and the driver at high speed.

Run: ``.venv/bin/python benchmarks/bench_sim_server.py [--speeds 1000 2000] [--hours 8]``

Prints, all measured in this one run, for the ``graphite-paper`` scenario
(512×512 frames, one every 256 s):

* the wall time to run the physics alone for the whole session
  (``SimulatedAFM.advance_to``, no server) — the floor for any speed;
* for each speed: the wall time until the driver, polling ``latest_frame()``
  over loopback TCP every 50 ms, has seen the session's last frame, next to
  the ideal ``hours·3600 / speed``; the frames received against those the
  simulator completed; the median and 95th-percentile reply time of the cheap
  ``FRAME:INDEX?`` query while the physics runs; and the frame transfer rate.

Target: an 8 h session of 256 s frames well under a minute at high speed.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time

from afmdrift.drivers import NanoScopeDriver
from afmdrift.drivers.sim import SimulatedAFM
from afmdrift.drivers.sim._server import SimulatorServer

SCENARIO = "graphite-paper"


def physics_only(duration_s: float) -> tuple[float, int]:
    sim = SimulatedAFM.from_scenario(SCENARIO)
    t0 = time.perf_counter()
    frames = sim.advance_to(duration_s)
    return time.perf_counter() - t0, len(frames)


async def over_the_wire(speed: float, duration_s: float) -> dict[str, float]:
    sim = SimulatedAFM.from_scenario(SCENARIO)
    async with SimulatorServer(sim, speed=speed) as server:
        port = await server.start_tcp(0)
        async with NanoScopeDriver(f"socket://127.0.0.1:{port}", timeout_s=10.0) as driver:
            wall0 = time.perf_counter()
            received: set[int] = set()
            latencies: list[float] = []
            last_end = 0.0
            while last_end < duration_s - sim.frame_period_s:
                q0 = time.perf_counter()
                await driver.frame_index()
                latencies.append(time.perf_counter() - q0)
                frame = await driver.latest_frame()
                if frame is not None:
                    received.add(frame.index)
                    last_end = frame.t_end_s
                await asyncio.sleep(0.05)
            wall = time.perf_counter() - wall0
            produced = (sim.latest_frame().index + 1) if sim.latest_frame() else 0
            transfers = driver.frame_transfers
    latencies.sort()
    return {
        "wall_s": wall,
        "ideal_s": duration_s / speed,
        "received": len(received),
        "produced": produced,
        "transfers": transfers,
        "median_ms": 1e3 * statistics.median(latencies),
        "p95_ms": 1e3 * latencies[int(0.95 * (len(latencies) - 1))],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds", type=float, nargs="+", default=[1000.0, 2000.0])
    ap.add_argument("--hours", type=float, default=8.0)
    args = ap.parse_args()
    duration_s = args.hours * 3600.0
    floor_s, n = physics_only(duration_s)
    print(f"scenario {SCENARIO}, {args.hours:g} h virtual")
    print(f"physics alone: {floor_s:.1f} s wall for {n} frames ({floor_s / n * 1e3:.0f} ms/frame)")
    for speed in args.speeds:
        r = asyncio.run(over_the_wire(speed, duration_s))
        print(
            f"speed {speed:g}: {r['wall_s']:.1f} s wall (ideal {r['ideal_s']:.1f} s, ratio "
            f"{r['wall_s'] / r['ideal_s']:.2f}; physics floor ratio {r['wall_s'] / floor_s:.2f}), "
            f"frames received {r['received']:.0f} of {r['produced']:.0f} "
            f"({r['transfers']:.0f} transfers), FRAME:INDEX? median {r['median_ms']:.1f} ms, "
            f"p95 {r['p95_ms']:.1f} ms"
        )


if __name__ == "__main__":
    main()

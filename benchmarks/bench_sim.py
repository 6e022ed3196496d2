"""Speed of the simulated AFM: rendering one frame and recording whole sessions.

Run: ``.venv/bin/python benchmarks/bench_sim.py [--skip-record]``

Prints, all measured in this one run:

* median time to scan one 512×512 frame of the ``graphite-paper`` and
  ``gold-manipulation-8h`` samples (target well under 100 ms), next to the bare
  cubic-spline lookup (``scipy.ndimage.map_coordinates``) of the same number of
  points and the ratio of the two;
* wall time of ``record_session`` for each built-in scenario (target for the
  8 h 512×512 scenarios: well under a minute), with frames per second and the
  drift statistics of the recorded truth.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from afmdrift.drivers.sim import SimulatedAFM
from afmdrift.drivers.sim._record import record_session

SCENARIOS = ("graphite-paper", "gold-manipulation-8h", "quiet-lab-24h", "hsafm-movie", "default")


def frame_times(name: str, n: int = 8) -> list[float]:
    sim = SimulatedAFM.from_scenario(name)
    sim.advance_to(1.0)  # generate physics and sample once
    period = sim.frame_period_s
    times = []
    t = 1.0
    for _ in range(n):
        t += period
        t0 = time.perf_counter()
        sim.advance_to(t)
        times.append(time.perf_counter() - t0)
    return times


def bare_lookup(n: int = 8) -> list[float]:
    coeffs = ndimage.spline_filter(np.random.default_rng(0).random((2048, 2048)), order=3)
    rows, cols = np.mgrid[0:512, 0:512].astype(np.float64)
    times = []
    for k in range(n):
        t0 = time.perf_counter()
        ndimage.map_coordinates(
            coeffs, [rows + 0.37 * k, cols + 100.3], order=3, mode="grid-wrap", prefilter=False
        )
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-record", action="store_true", help="only time single frames")
    args = parser.parse_args()
    bare = statistics.median(bare_lookup())
    print(f"bare spline lookup, 512x512 points: {bare * 1e3:.1f} ms")
    for name in SCENARIOS[:2]:
        med = statistics.median(frame_times(name))
        print(f"{name}: one 512x512 frame {med * 1e3:.1f} ms ({med / bare:.2f}x the bare lookup)")
    if args.skip_record:
        return
    with tempfile.TemporaryDirectory() as tmp:
        for name in SCENARIOS:
            s = record_session(name, Path(tmp) / name)
            st = s.stats
            print(
                f"record {name}: {s.frames} frames over {s.duration_s:.0f} s virtual in "
                f"{s.wall_s:.1f} s wall ({s.frames / s.wall_s:.1f} frames/s); drift mean speed "
                f"{st['mean_speed_nm_per_s']:.3f} nm/s, excursion {st['excursion_nm']:.1f} nm, "
                f"RMS frame step {st['rms_frame_step_nm']:.2f} nm, "
                f"max frame step {st['max_frame_step_nm']:.2f} nm"
            )


if __name__ == "__main__":
    main()

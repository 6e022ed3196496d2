"""Speed of ``afmdrift measure STACK``, the path users run on recorded stacks.

Run: ``.venv/bin/python benchmarks/bench_measure.py [--frames N] [--movie-frames M] [--block N]``

Two streams, each timed frame by frame and interleaved so that all figures
see the same machine load:

* a 512² particle stack (2 nm/px, SNR 10, on a slow closed path of ±40 px), the
  default 64/128 blocks;
* a 200² HS-AFM-like movie (smooth texture, 0.5 nm/px, SNR 10), with the
  automatic block size (32/64 px).

For every frame: the step of :func:`afmdrift.runs.track_stack` (what
``afmdrift measure STACK`` runs per frame: the daemon's position component,
the drift trajectory, the record), :meth:`DriftTracker.update` alone on the
same frame, and the bare FFTW transforms the frame needs (one forward and one
pruned inverse real FFT of every block, split into the engine's batches and
taken in turn by the engine's threads; see ``bench_registration.py``).
Printed: medians, the ratios measure/tracker and measure/FFT floor, and frames
per second.

``--block N`` alternates the three paths in rounds of N frames instead, each
round back to back as a stream runs (``afmdrift measure`` measures frame
after frame). Frame by frame, each path's worker thread sits idle or busy
with another engine's data for the other two paths' 5 ms before every
frame, which a streaming user never has; on this VM a measure step after a
5 ms pause takes 0.3-0.5 ms longer (``RESULTS.md``, 2026-11-26).

Then the whole command (``afmdrift measure STACK.npy``, start-up and file
reading included) is run once on the 512² stack saved as float32,
as a user runs it: its wall time and peak resident memory; then on four
times and on a sixth of the frames, three times each, so that the median
difference gives the command's time per frame from outside (reading, the
pipeline and the JSON line written), next to the FFT floor of the same run.

The command-line process runs OpenBLAS on one thread (``afmdrift.cli``); this
benchmark sets the same before NumPy loads, so the in-process figures are
those of the command.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_registration import BareFFT

from afmdrift.config import AfmdriftConfig
from afmdrift.io import AfmImage
from afmdrift.registration import DriftTracker
from afmdrift.registration._blocks import config_for_image
from afmdrift.registration._engine import BlockEngine
from afmdrift.runs import track_stack
from afmdrift.testing import TextureShifter, add_noise, particle_texture, rough_texture


def stack(kind: str, n: int, rng: np.random.Generator) -> tuple[list[np.ndarray], float]:
    """``n`` frames of the given kind drifting slowly, and their pixel size (nm)."""
    if kind == "512":
        tex = particle_texture((700, 700), pixel_size_nm=2.0, rng=rng)
        shape, pixel = (512, 512), 2.0
    else:
        tex = rough_texture((320, 320), pixel_size_nm=0.5, rng=rng, correlation_length_nm=2.0)
        shape, pixel = (200, 200), 0.5
    shifter = TextureShifter(tex)
    # a slow back-and-forth path, so a long movie stays inside the texture
    phase = np.linspace(0.0, 2.0 * np.pi, n)
    amp = 40.0 if kind == "512" else 30.0
    frames = [
        add_noise(
            shifter.crop(
                shape,
                dx_px=amp * np.sin(phase[k]),
                dy_px=0.5 * amp * np.sin(2 * phase[k]),
            ),
            snr=10.0,
            rng=rng,
        )
        for k in range(n)
    ]
    return frames, pixel


def images(frames: list[np.ndarray], pixel: float) -> list[AfmImage]:
    return [
        AfmImage(heights_nm=f, pixel_size_nm=(pixel, pixel), path=Path("bench.npy"), frame=k)
        for k, f in enumerate(frames)
    ]


def run(kind: str, n: int, rng: np.random.Generator, block: int = 1) -> dict[str, float]:
    """Time the three paths on one stream, alternating in rounds of
    ``block`` frames (1: frame by frame)."""
    frames, pixel = stack(kind, n, rng)
    config = AfmdriftConfig()
    cfg = config_for_image(config.registration, frames[0])
    bare = BareFFT(BlockEngine(frames[0].shape, cfg), cfg, batched=True)
    tracker = DriftTracker(pixel_size_nm=pixel, config=config.registration)
    steps = track_stack(images(frames, pixel), config)
    measure_ms: list[float] = []
    tracker_ms: list[float] = []
    fft_ms: list[float] = []
    valid = 0
    tracker.update(frames[0])
    for start in range(1, n, block):
        ks = range(start, min(n, start + block))
        for _ in ks:
            t0 = time.perf_counter()
            doc = next(steps)
            measure_ms.append(1e3 * (time.perf_counter() - t0))
            valid += bool(doc["valid"])
        for k in ks:
            t0 = time.perf_counter()
            tracker.update(frames[k])
            tracker_ms.append(1e3 * (time.perf_counter() - t0))
        for _ in ks:
            fft_ms.append(1e3 * bare.time()[0])
    # the first frames compile and plan: leave them out
    skip = min(5, len(measure_ms) // 4)
    m = statistics.median(measure_ms[skip:])
    t = statistics.median(tracker_ms[skip:])
    f = statistics.median(fft_ms[skip:])
    return {
        "frames": n,
        "valid": valid,
        "measure_ms": m,
        "tracker_ms": t,
        "fft_ms": f,
        "measure_over_tracker": m / t,
        "measure_over_fft": m / f,
        "measure_fps": 1e3 / m,
        "blocks": cfg.block_size,
    }


def command_wall_s(n: int, rng: np.random.Generator) -> tuple[float, int, float]:
    """Wall time (s), JSON lines and peak resident memory (MB) of ``afmdrift
    measure STACK.npy`` on an ``n``-frame 512² float32 stack."""
    frames, pixel = stack("512", n, rng)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "stack.npy"
        np.save(path, np.stack(frames).astype(np.float32))
        del frames
        exe = Path(sys.executable).with_name("afmdrift")
        out_path = Path(tmp) / "out.jsonl"
        t0 = time.perf_counter()
        with out_path.open("w") as sink:
            proc = subprocess.Popen(
                [str(exe), "measure", str(path), "--pixel-size-nm", str(pixel)],
                stdout=sink,
                stderr=subprocess.DEVNULL,
            )
            # The command's high-water resident memory, read while it runs:
            # its rusage would count this (large) process's pages, which the
            # child shares until it executes the command.
            peak_kb = 0
            status = Path(f"/proc/{proc.pid}/status")
            while proc.poll() is None:
                try:
                    for line in status.read_text().splitlines():
                        if line.startswith("VmHWM:"):
                            peak_kb = max(peak_kb, int(line.split()[1]))
                except (OSError, ValueError):
                    pass
                time.sleep(0.01)
        wall = time.perf_counter() - t0
        out = out_path.read_text()
    peak_mb = peak_kb / 1024 if peak_kb else float("nan")
    return wall, out.count("\n"), peak_mb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=120, help="512² frames (120)")
    ap.add_argument("--movie-frames", type=int, default=600, help="200² frames (600)")
    ap.add_argument(
        "--block", type=int, default=1, help="frames per round of each path (1: interleaved)"
    )
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    floor_ms = {}
    for kind, n in (("512", args.frames), ("200", args.movie_frames)):
        r = run(kind, n, rng, max(1, args.block))
        floor_ms[kind] = r["fft_ms"]
        print(
            f"{kind}² ({r['blocks']:.0f} px blocks), {r['frames']:.0f} frames, "
            f"{r['valid']:.0f} valid: measure {r['measure_ms']:.2f} ms/frame "
            f"({r['measure_fps']:.0f} frames/s), tracker {r['tracker_ms']:.2f} ms, "
            f"FFT floor {r['fft_ms']:.2f} ms; measure/tracker {r['measure_over_tracker']:.2f}x, "
            f"measure/FFT floor {r['measure_over_fft']:.2f}x"
        )
    wall, lines, peak_mb = command_wall_s(args.frames, rng)
    print(
        f"afmdrift measure STACK.npy (512², {args.frames} frames, float32): {wall:.2f} s wall, "
        f"{lines} JSON lines, {1e3 * wall / max(1, args.frames - 1):.1f} ms per frame "
        f"with start-up and reading; peak resident memory {peak_mb:.0f} MB"
    )
    # The command from outside, per frame: the difference of two runs, so that
    # start-up (imports, plans, compiled kernels) cancels and reading, the
    # pipeline and writing each frame's JSON line remain. Start-up varies by
    # a tenth of a second from run to run: a long stack and the median of
    # three pairs keep that under 0.1 ms per frame.
    many, few = 4 * args.frames, max(2, args.frames // 6)
    pairs = [(command_wall_s(many, rng)[0], command_wall_s(few, rng)[0]) for _ in range(3)]
    per_frame_ms = statistics.median(1e3 * (a - b) / (many - few) for a, b in pairs)
    print(
        f"afmdrift measure STACK.npy from outside, per frame ({many} - {few} frames, median "
        f"of 3): {per_frame_ms:.2f} ms; FFT floor {floor_ms['512']:.2f} ms; "
        f"command/FFT floor {per_frame_ms / floor_ms['512']:.2f}x"
    )


if __name__ == "__main__":
    main()

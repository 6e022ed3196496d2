"""Speed and memory of the block phase-correlation engine on a 512×512 stream.

Run: ``.venv/bin/python benchmarks/bench_registration.py [--frames N] [--threads T ...]``

Prints, all measured in this one run, for each thread count (default 1 and
2, interleaved frame by frame so that all see the same machine load):

* median time of :meth:`DriftTracker.update` per new frame (target ≤ 5 ms);
* median time of the bare FFTW work one frame needs (one forward and one
  inverse real FFT of every block, on separately planned arrays, split into
  the engine's batches and taken in turn by the same number of threads,
  timed right after each frame) and the ratio of the two (target ≤ 2×); also the bare
  transforms as one plan with FFTW's own threads (the alternative way to use
  two cores; timed in a pass after the stream, because FFTW's threads spin
  for a while after each transform and slow what runs next), and the CPU
  time of this process;
* the time of a loop of scikit-image ``phase_cross_correlation`` over the same
  windowed blocks (upsample factor 20) and our speed-up over it;
* resident memory (psutil RSS) at the start and end of the stream (flat).

With ``--accuracy`` it prints instead the sub-pixel method comparison of
``docs/registration.md``: RMS frame error of each ``subpixel`` method over
random shifts within ±40 px, noise-free and at SNR 10.

The stream is a particle texture at SNR 10 drifting on a smooth closed path;
a pool of frames is rendered once and replayed in order, so the path stays
continuous however many frames are run.
"""

from __future__ import annotations

import argparse
import gc
import itertools
import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import psutil

from afmdrift.registration import DriftTracker, RegistrationConfig
from afmdrift.registration._blocks import raised_cosine
from afmdrift.registration._engine import BlockEngine
from afmdrift.registration._fftw import BatchedRealFFT, resolve_wisdom_path
from afmdrift.testing import add_noise, particle_texture, shifted_crop

SHAPE = (512, 512)
POOL = 64
PIXEL_NM = 2.0


def make_pool(rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    """Frames along a closed path ``d(i)`` (px), one period per pool."""
    tex = particle_texture((640, 640), pixel_size_nm=PIXEL_NM, rng=rng)
    phase = 2.0 * np.pi * np.arange(POOL) / POOL
    path = np.column_stack([6.0 * np.sin(phase), 4.0 * np.sin(2.0 * phase)])
    frames = [
        add_noise(shifted_crop(tex, shape=SHAPE, dx_px=dx, dy_px=dy), snr=10.0, rng=rng).astype(
            np.float32
        )
        for dx, dy in path
    ]
    return frames, path


class BareFFT:
    """The bare transforms one frame needs, on separately planned arrays:
    one forward and one inverse batched real FFT over every block (the
    inverse pruned to the rows of the search region, as the engine's).

    ``batched``: the engine's split into batches of ``BATCH_BLOCKS`` on
    single-threaded plans, each of ``threads`` threads with its own plans
    and arrays per batch size, taking the batches in turn the way the engine
    does; otherwise one plan over all blocks with FFTW's own ``threads``.
    """

    def __init__(self, engine: BlockEngine, cfg: RegistrationConfig, *, batched: bool) -> None:
        wisdom = resolve_wisdom_path(cfg.fftw_wisdom)

        def plan(size: int, threads: int) -> BatchedRealFFT:
            return BatchedRealFFT(
                size,
                engine.layout.ext,
                threads=threads,
                planner=cfg.fftw_planner,
                wisdom_path=wisdom,
                out_rows=2 * engine.layout.max_shift[0] + 1,
            )

        n = engine.layout.n_blocks
        self.sizes = [b.stop - b.start for b in engine._batches] if batched else [n]
        threads = min(cfg.threads, len(self.sizes)) if batched else 1
        self.plans: list[dict[int, BatchedRealFFT]] = [
            {size: plan(size, 1 if batched else cfg.threads) for size in set(self.sizes)}
            for _ in range(threads)
        ]
        self.inputs = {
            id(fft): np.random.default_rng(0).standard_normal(fft.real.shape).astype(np.float32)
            for plans in self.plans
            for fft in plans.values()
        }
        self.pool = ThreadPoolExecutor(max_workers=threads - 1) if threads > 1 else None

    def _run(self, t: int, order: itertools.count[int]) -> None:
        plans = self.plans[t]
        while (i := next(order)) < len(self.sizes):
            fft = plans[self.sizes[i]]
            fft.forward()
            fft.inverse()

    def time(self) -> tuple[float, float]:
        """Wall and CPU seconds for one frame's forward plus inverse transforms.

        The inputs are refilled before timing (not counted): each round trip
        scales the data by the block size, and one thread runs at most 8
        batches through the same arrays, so the values stay finite (×2^112 at
        most).
        """
        for plans in self.plans:
            for fft in plans.values():
                fft.real[:] = self.inputs[id(fft)]
        order = itertools.count()
        t0, c0 = time.perf_counter(), time.process_time()
        if self.pool is None:
            self._run(0, order)
        else:
            futures = [self.pool.submit(self._run, t, order) for t in range(1, len(self.plans))]
            self._run(0, order)
            for f in futures:
                f.result()
        return time.perf_counter() - t0, time.process_time() - c0


def skimage_ms(engine: BlockEngine, ref: np.ndarray, cur: np.ndarray, repeats: int) -> float:
    """One frame's worth of scikit-image phase_cross_correlation on the blocks."""
    from skimage.registration import phase_cross_correlation

    lay = engine.layout
    ey, ex = lay.ext
    win = raised_cosine(ey, ex)
    g_ref = engine.gradient(ref)
    g_cur = engine.gradient(cur)
    blocks = [
        (g_ref[t : t + ey, le : le + ex] * win, g_cur[t : t + ey, le : le + ex] * win)
        for t, le in zip(lay.top, lay.left, strict=True)
    ]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for a, b in blocks:
            phase_cross_correlation(a, b, upsample_factor=20, normalization="phase")
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def accuracy_table(pairs: int) -> None:
    """RMS error of each sub-pixel method on 512×512 particle frames."""
    import math

    from afmdrift.registration import measure_drift
    from afmdrift.testing import TextureShifter

    shifter = TextureShifter(
        particle_texture((640, 640), pixel_size_nm=PIXEL_NM, rng=np.random.default_rng(1))
    )
    print(f"sub-pixel methods, {pairs} random shifts within +-40 px, 512x512 particle frames")
    print(f"{'method':10s} {'SNR':>6s} {'RMS px':>8s} {'max px':>8s} {'valid':>6s} {'blocks':>7s}")
    for snr in (None, 10.0):
        for method in ("dft", "sinc", "parabolic", "gaussian"):
            rng = np.random.default_rng(2)
            errors = []
            blocks = []
            cfg = RegistrationConfig(subpixel=method)
            for _ in range(pairs):
                d = rng.uniform(-40.0, 40.0, 2)
                a = shifter.crop(SHAPE)
                b = shifter.crop(SHAPE, dx_px=float(d[0]), dy_px=float(d[1]))
                if snr is not None:
                    a = add_noise(a, snr=snr, rng=rng)
                    b = add_noise(b, snr=snr, rng=rng)
                r = measure_drift(a, b, pixel_size_nm=PIXEL_NM, config=cfg)
                blocks.append(r.valid_blocks)
                if r.valid:
                    errors.append((r.dx_px - d[0], r.dy_px - d[1]))
            err = np.asarray(errors)
            rms = math.sqrt(float(np.mean(err**2))) if err.size else math.nan
            worst = float(np.max(np.abs(err))) if err.size else math.nan
            label = "inf" if snr is None else f"{snr:g}"
            print(
                f"{method:10s} {label:>6s} {rms:8.4f} {worst:8.4f} "
                f"{len(errors):3d}/{pairs:<2d} {np.mean(blocks):7.1f}"
            )


@dataclass
class StreamTimes:
    """Per-frame wall and CPU seconds of one configuration in the stream."""

    threads: int
    tracker: DriftTracker
    bare_batched: BareFFT
    bare_fftw: BareFFT
    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    bare_wall: list[float] = field(default_factory=list)
    bare_cpu: list[float] = field(default_factory=list)
    fftw_wall: list[float] = field(default_factory=list)
    errors: list[np.ndarray] = field(default_factory=list)
    positions: list[tuple[float, float]] = field(default_factory=list)


def ms(values: list[float]) -> float:
    return 1e3 * statistics.median(values)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1000, help="frames in the stream (1000)")
    ap.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[1, 2],
        help="thread counts timed side by side (default: 1 2)",
    )
    ap.add_argument("--skimage-repeats", type=int, default=3, help="skimage frames timed (3)")
    ap.add_argument(
        "--accuracy", action="store_true", help="print the sub-pixel method comparison instead"
    )
    args = ap.parse_args()
    if args.accuracy:
        accuracy_table(24)
        return

    rng = np.random.default_rng(2008)
    frames, path = make_pool(rng)
    proc = psutil.Process()
    runs = []
    for threads in args.threads:
        cfg = RegistrationConfig(threads=threads, gradient="x")
        engine = BlockEngine(SHAPE, cfg)
        runs.append(
            StreamTimes(
                threads=threads,
                tracker=DriftTracker(pixel_size_nm=PIXEL_NM, config=cfg),
                bare_batched=BareFFT(engine, cfg, batched=True),
                bare_fftw=BareFFT(engine, cfg, batched=False),
            )
        )
    for run in runs:
        run.tracker.update(frames[0])
        for i in range(1, 2 * POOL + 1):  # warm-up: plans, allocator pools, caches
            run.tracker.update(frames[i % POOL])
            run.bare_batched.time()
            run.bare_fftw.time()
        run.tracker.reset()
        run.tracker.update(frames[0])
    gc.collect()
    rss_start = proc.memory_info().rss
    load_start = psutil.getloadavg()[0]
    for i in range(1, args.frames + 1):
        frame = frames[i % POOL]
        # Interleaved frame by frame, so every configuration and its bare
        # transforms see the same machine load.
        for run in runs:
            t0, c0 = time.perf_counter(), time.process_time()
            step = run.tracker.update(frame)
            run.wall.append(time.perf_counter() - t0)
            run.cpu.append(time.process_time() - c0)
            wall, cpu = run.bare_batched.time()
            run.bare_wall.append(wall)
            run.bare_cpu.append(cpu)
            if step is not None and step.accepted:
                run.errors.append(np.subtract(step.position_px, path[i % POOL] - path[0]))
                run.positions.append(step.position_px)
    rss_end = proc.memory_info().rss
    load_end = psutil.getloadavg()[0]
    # FFTW's own threads keep spinning for a few ms after each transform,
    # which slowed whatever ran next by up to 50 % in CPU time: time them in
    # a pass of their own after the stream.
    for run in runs:
        for _ in range(args.frames):
            run.fftw_wall.append(run.bare_fftw.time()[0])

    engine = BlockEngine(SHAPE, RegistrationConfig(gradient="x"))
    lay = engine.layout
    print(
        f"frames: {args.frames} of {SHAPE[1]}x{SHAPE[0]} px, {lay.n_blocks} blocks of "
        f"{lay.ext[1]}x{lay.ext[0]} in {engine.n_batches} batches, CPUs {psutil.cpu_count()}, "
        f"load average {load_start:.2f} at start, {load_end:.2f} at end"
    )
    print(
        f"{'threads':>7s} {'update ms':>10s} {'bare ms':>8s} {'ratio':>6s} "
        f"{'FFTW-own-threads bare ms':>25s} {'CPU ms ours/bare':>17s} {'RMS err px':>11s}"
    )
    for run in runs:
        ours, bare = ms(run.wall), ms(run.bare_wall)
        err = np.asarray(run.errors)
        rms = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
        print(
            f"{run.threads:7d} {ours:10.2f} {bare:8.2f} {ours / bare:5.2f}x "
            f"{ms(run.fftw_wall):25.2f} {ms(run.cpu):8.2f}/{ms(run.bare_cpu):<8.2f} {rms:11.4f}"
        )
    best = min(runs, key=lambda r: ms(r.wall))
    print(
        f"targets: <= 5 ms/frame -> {ms(best.wall):.2f} ms with {best.threads} thread(s); "
        f"<= 2x bare -> {ms(best.wall) / ms(best.bare_wall):.2f}x"
    )
    same = all(r.positions == runs[0].positions for r in runs)
    print(f"tracks identical across thread counts: {same}")
    sk = skimage_ms(engine, frames[0], frames[1], args.skimage_repeats)
    print(
        f"skimage phase_cross_correlation x{lay.n_blocks}: {sk:.2f} ms/frame "
        f"({sk / ms(best.wall):.1f}x slower)"
    )
    print(
        f"RSS start / end / growth: {rss_start / 2**20:.1f} / {rss_end / 2**20:.1f} / "
        f"{(rss_end - rss_start) / 2**20:+.2f} MiB"
    )
    err = np.asarray(best.errors)
    if err.size:
        print(
            f"position error vs truth: RMS {np.sqrt(np.mean(err**2)):.4f} px, "
            f"max {np.max(np.abs(err)):.4f} px over {len(err)} accepted frames"
        )


if __name__ == "__main__":
    main()

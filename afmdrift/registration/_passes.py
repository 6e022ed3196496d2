"""A block pass on the engine's threads: the split of the blocks into
batches, the window placement, one thread's share of the batches with every
step (FFTs included) in one compiled call without the GIL, the assembly of
the block vectors, and the threads that run it (:class:`PassThreads`: a
process-wide worker pool, each thread with its own FFTW plans and work
arrays, the shared batch counter and the gate a worker waits at).

Results do not depend on the thread count: every block is computed on its
own, in a fixed order, and the split into batches is fixed by the frame
layout.
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift._cores import available_cores
from afmdrift.registration._blocks import FrameStats, gradient_and_stats
from afmdrift.registration._constants import KernelConstants
from afmdrift.registration._fftw import BatchedRealFFT, Planner
from afmdrift.registration._intrinsics import atomic_load, fetch_add, fftw_execute, publish
from afmdrift.registration._jit import jit
from afmdrift.registration._peaks import pick_peaks
from afmdrift.registration._selection import masked_medians
from afmdrift.registration._spectra import forward_strips, normalise_cross
from afmdrift.registration._subpixel import dft_subpixel, subpixel_3pt

__all__ = [
    "BATCH_BLOCKS",
    "GATE_SPINS",
    "BatchTable",
    "BlockVectors",
    "GradientTail",
    "PassArrays",
    "PassRun",
    "PassThreads",
    "Peaks",
    "Placement",
    "ThreadWork",
    "Windows",
    "assemble",
    "batch_blocks",
    "batch_split",
    "join",
    "measure_batches",
    "place_windows",
    "thread_work",
    "wait",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]
U64 = npt.NDArray[np.uint64]

#: Blocks per batch, the engine's unit of work: a batch goes through every
#: pass (window, forward FFT, normalisation, inverse FFT, peaks, sub-pixel)
#: before the next starts, so its work arrays (about 1 MB for 8 blocks of
#: 128²) stay near the core instead of streaming the whole block stack
#: through memory once per pass. The engine's threads take the batches in
#: turn (see :class:`PassThreads`), so a thread on a slower core simply does
#: fewer (virtual CPUs can differ in speed from minute to minute, and a fixed
#: half of the blocks on the slower one would set the frame's time). The last
#: ``2 * BATCH_BLOCKS`` blocks go in half batches, so that the threads end
#: closer together and neither waits long for the other's last batch
#: (figures in benchmarks/RESULTS.md). The split into batches depends only
#: on the layout (:func:`batch_split`).
BATCH_BLOCKS = 8
#: Window area (px²) for which a batch holds BATCH_BLOCKS blocks; smaller
#: windows go in proportionally larger batches (the same work arrays' size),
#: so that per-batch call overhead stays small against the arithmetic.
BATCH_WINDOW_PX2 = 128 * 128
#: Reads of a pass's gate before a worker that spins on it waits in Python
#: instead (about 0.3 ms at 0.6 ns per read here; the gate usually opens
#: within 0.1 ms of the worker reaching it, once the calling thread has
#: completed and checked the gradient image).
GATE_SPINS = 500_000

_pool_lock = threading.Lock()
_pools: dict[int, ThreadPoolExecutor] = {}


def _forget_pools_after_fork() -> None:
    # A forked child has none of the parent's worker threads: a pool taken
    # over from the parent would queue work that never runs.
    global _pool_lock
    _pool_lock = threading.Lock()
    _pools.clear()


os.register_at_fork(after_in_child=_forget_pools_after_fork)


def _worker_pool(workers: int) -> ThreadPoolExecutor:
    """Process-wide persistent pool of ``workers`` threads (made on first use).

    The calling thread always takes batches itself, so ``threads`` threads
    use ``threads - 1`` pool workers. Workers never submit work themselves,
    so sharing the pool between engines and calling threads cannot deadlock.
    """
    with _pool_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="afmdrift-reg")
            _pools[workers] = pool
        return pool


def batch_blocks(ext: tuple[int, int]) -> int:
    """Blocks per batch for windows of ``ext`` px: :data:`BATCH_BLOCKS` for
    128² windows, more for smaller ones (the same work array size: 32 for
    64² windows)."""
    return BATCH_BLOCKS * max(1, BATCH_WINDOW_PX2 // max(1, ext[0] * ext[1]))


def batch_split(n: int, size: int = BATCH_BLOCKS) -> tuple[slice, ...]:
    """Batches of ``size`` of ``n`` blocks; the last ``2 * size`` blocks,
    and what does not fill a whole batch before them, in batches of half
    that size."""
    tail_start = max(0, n - 2 * size)
    tail_start -= tail_start % size
    half = max(1, size // 2)
    starts = [*range(0, tail_start, size), *range(tail_start, n, half)]
    stops = [*starts[1:], n]
    return tuple(slice(a, b) for a, b in zip(starts, stops, strict=True))


class Windows(NamedTuple):
    """A gradient image ``(rows, cols)`` and the corners of its block
    windows, ``(n,)`` each."""

    grad: F32
    top: IArr
    left: IArr


class Peaks(NamedTuple):
    """Per-block integer peak ``(sy, sx)``, its correlation value and MSE, and
    the sub-pixel offset ``(fy, fx)`` with whether it converged (all blocks
    of a frame; each batch writes its blocks')."""

    sy: IArr
    sx: IArr
    fy: F64
    fx: F64
    ok: BArr
    peak: F32
    mse: F64

    @classmethod
    def empty(cls, n: int) -> Peaks:
        """Uninitialised arrays (every block's entries are written by the
        peak search and the sub-pixel step), in four allocations."""
        sy, sx = np.empty((2, n), dtype=np.intp)
        fy, fx, mse = np.empty((3, n))
        return cls(
            sy=sy,
            sx=sx,
            fy=fy,
            fx=fx,
            ok=np.empty(n, dtype=bool),
            peak=np.empty(n, dtype=np.float32),
            mse=mse,
        )


class ThreadWork(NamedTuple):
    """One thread's FFTW plans and work arrays, with room for the largest
    batch."""

    #: ``plans[kind]``: the plans of
    #: :class:`afmdrift.registration._fftw.BatchedRealFFT` for batches of the
    #: ``kind``-th size, all on these arrays.
    plans: U64
    #: Addresses of the arrays the plans were made on (``BatchedRealFFT.pointers``).
    pointers: U64
    #: Spectra (interleaved float32) and the pruned inverse's output.
    spec: F32
    corr: F32
    #: The weighted cross-power band of the ``dft`` sub-pixel step
    #: (interleaved float32; no blocks for the other methods).
    band: F32
    #: Windowed image rows and their transforms (interleaved float32) of
    #: :func:`~afmdrift.registration._spectra.forward_strips`, and its scratch.
    strip: F32
    strip_spec: F32
    base: IArr


def thread_work(ffts: Sequence[BatchedRealFFT], band: F32) -> ThreadWork:
    """The record of one thread's plans for each batch size (``ffts``,
    largest first, all on the first one's arrays) and its ``band`` array."""
    first = ffts[0]
    return ThreadWork(
        plans=np.stack([fft.plans for fft in ffts]),
        pointers=first.pointers,
        spec=first.spectrum.view(np.float32),
        corr=first.out,
        band=band,
        strip=first.strip,
        strip_spec=first.strip_spectrum.view(np.float32),
        base=np.empty(first.real.shape[0], dtype=np.intp),
    )


class BatchTable(NamedTuple):
    """Batch ``i`` is the blocks ``order[starts[i]:stops[i]]``, with the plans
    of its size ``kinds[i]``."""

    starts: IArr
    stops: IArr
    kinds: IArr


class PassArrays(NamedTuple):
    """What a block pass reads and writes, shared by its threads (per-block
    arrays cover every block of the frame)."""

    #: The blocks in the order the batches take them.
    order: IArr
    #: The current frame's and the reference's windows.
    cur: Windows
    ref: Windows
    #: The reference's normalised spectra (interleaved int16) and their
    #: magnitudes in the sub-pixel band.
    ref_conj: npt.NDArray[np.int16]
    ref_band_mag: F32
    #: Written: the current spectra as a next reference (no blocks: not
    #: kept) and their magnitudes in the sub-pixel band.
    keep: npt.NDArray[np.int16]
    band_mag: F32
    #: ``(ry, rx, my, mx)``: the peak search within ``±(ry, rx)`` of the
    #: correlation's centre ``(my, mx)``.
    search: IArr
    #: Written: the peaks and sub-pixel offsets.
    peaks: Peaks


class Placement(NamedTuple):
    """Window corners ``(n,)`` of the current frame, and where they sit:
    ``placed`` without clamping, ``near`` clamped by at most half the search."""

    top: IArr
    left: IArr
    placed: BArr
    near: BArr


class BlockVectors(NamedTuple):
    """Block vectors ``(n, 2)`` ``(x, y)``, whether each was measured, the peak
    confidence, and the median ``(x, y)`` of the measured vectors."""

    vectors: F64
    measured: BArr
    confidence: F64
    median: F64


@jit
def place_windows(ref_top, ref_left, dy, dx, bounds, out):  # type: ignore[no-untyped-def]
    """Window corners moved by the integer shift ``(dy, dx)`` and clamped
    into ``[0, max_top] × [0, max_left]``; ``placed`` where no clamping was
    needed, ``near`` where it was at most ``(near_y, near_x)`` (``bounds =
    (max_top, max_left, near_y, near_x)``), into ``out`` (a
    :class:`Placement`). Returns the number of placed windows."""
    max_top, max_left, near_y, near_x = bounds
    top, left, placed, near = out
    count = 0
    for i in range(ref_top.size):
        want_t = ref_top[i] + dy
        want_l = ref_left[i] + dx
        t = min(max(want_t, 0), max_top)
        le = min(max(want_l, 0), max_left)
        top[i] = t
        left[i] = le
        placed[i] = t == want_t and le == want_l
        near[i] = abs(t - want_t) <= near_y and abs(le - want_l) <= near_x
        count += 1 if placed[i] else 0
    return count


@jit
def assemble(frame, near, unbias, area, out):  # type: ignore[no-untyped-def]
    """Block vectors ``(x, y)`` = window move + ``unbias`` (n, 2, 2) times
    (integer peak + sub-pixel offset), the shift under the window corrected
    for the block's window response (``BlockEngine.calibrate``), and
    whether each block was measured: window ``near`` its place, a
    verified (finite-MSE) peak inside the search (not on its edge), and a
    converged sub-pixel step. Also the peak ``confidence = peak / area``
    (the inverse FFT's scale), in place NaN for an infinite ``mse`` (no
    candidate verified), and the medians of the measured vectors; into
    ``out`` (a :class:`BlockVectors`) from the pass ``frame`` (a
    :class:`PassArrays`). Returns the number of measured blocks."""
    cur, ref, p = frame.cur, frame.ref, frame.peaks
    my, mx = frame.search[0], frame.search[1]
    vectors, measured, confidence = out.vectors, out.measured, out.confidence
    for i in range(cur.top.size):
        rx = p.sx[i] + p.fx[i]
        ry = p.sy[i] + p.fy[i]
        vectors[i, 0] = (cur.left[i] - ref.left[i]) + unbias[i, 0, 0] * rx + unbias[i, 0, 1] * ry
        vectors[i, 1] = (cur.top[i] - ref.top[i]) + unbias[i, 1, 0] * rx + unbias[i, 1, 1] * ry
        finite = np.isfinite(p.mse[i])
        measured[i] = near[i] and finite and p.ok[i] and abs(p.sy[i]) < my and abs(p.sx[i]) < mx
        if not finite:
            p.mse[i] = np.nan
        confidence[i] = np.float64(p.peak[i]) / area
    return masked_medians(vectors, measured, out.median)


@jit
def _measure_batch(a, b, kind, thread, frame, c):  # type: ignore[no-untyped-def]
    """Blocks ``frame.order[a:b]`` through every step: window and forward FFT
    (:func:`~afmdrift.registration._spectra.forward_strips`), normalised
    cross-power spectrum, pruned inverse FFT, candidate peaks with their MSE
    check, sub-pixel offsets (see :func:`measure_batches`)."""
    nb = b - a
    blocks = frame.order[a:b]
    plans = thread.plans[kind]
    execute = c.transform.execute
    pointers = thread.pointers
    forward_strips(c.transform, frame.cur, blocks, plans, thread)
    band = thread.band[:nb] if thread.band.shape[0] > 0 else thread.band
    normalise_cross(
        c.spectrum, blocks, thread.spec[:nb], frame.ref_conj, frame.ref_band_mag, frame.keep,
        frame.band_mag, band,
    )  # fmt: skip
    fftw_execute(execute[1], plans[1], pointers[1], pointers[1])
    fftw_execute(execute[2], plans[2], pointers[1], pointers[2])
    corr = thread.corr[:nb]
    pick_peaks(c.peaks, blocks, corr, frame.search, frame.cur, frame.ref, frame.peaks)
    if c.subpixel.method == 0:
        dft_subpixel(c.subpixel, blocks, band, frame.peaks)
    else:
        subpixel_3pt(c.subpixel, blocks, corr, frame.peaks)


@jit
def measure_batches(counter, gate, spins, table, thread, frame, c):  # type: ignore[no-untyped-def]
    """One thread's share of a block pass, without the GIL: batches ``i``
    of ``table`` (a :class:`BatchTable`) taken in turn from the shared
    ``counter[0]`` (int64) until none is left, once ``gate[0]`` (int64) is
    no longer 0: a worker waits for the gate here, spinning without the GIL,
    while the calling thread completes the gradient image. Returns False,
    having taken no batch, if the gate is still closed after ``spins`` reads
    (the caller then waits for it another way); True once no batch is left.

    ``thread``: the thread's own FFTW plans and work arrays (a
    :class:`ThreadWork`); ``frame``: what the pass reads and writes, shared
    by all threads (a :class:`PassArrays`); ``c``: the engine's
    :class:`~afmdrift.registration._constants.KernelConstants`, with the
    addresses of FFTW's execute functions (see
    :class:`afmdrift.registration._fftw.Fftwf`) that run the plans."""
    n = table.starts.size
    reads = 0
    while atomic_load(gate, 0) == 0:
        reads += 1
        if reads > spins:
            return False
    while True:
        i = fetch_add(counter, 0)
        if i >= n:
            return True
        _measure_batch(table.starts[i], table.stops[i], table.kinds[i], thread, frame, c)


class PassThreads:
    """The threads of an engine's block passes: the calling thread and
    ``threads - 1`` workers of a process-wide pool, each with its own FFTW
    plans (single-threaded, one per batch size, on work arrays for the
    largest batch) and work arrays. They take the batches in turn; a
    measuring pass is one compiled call per thread (:func:`measure_batches`).

    Parameters
    ----------
    batches : tuple of slice
        The batches, as slices of the block order (:func:`batch_split`).
    threads : int
        Threads to use (no more than the batches).
    block_shape : (int, int)
        ``(Ey, Ex)`` of the windows.
    band_shape : (int, int)
        Shape of one block's sub-pixel band.
    dft : bool
        Whether the ``dft`` sub-pixel step needs each thread's band array.
    planner, wisdom_path
        FFTW planner effort and wisdom file (see
        :class:`~afmdrift.registration._fftw.BatchedRealFFT`).
    out_rows : int
        Rows of the pruned inverse transform's output.
    constants : KernelConstants
        The engine's kernel constants, for the compiled passes.
    """

    def __init__(
        self,
        batches: tuple[slice, ...],
        *,
        threads: int,
        block_shape: tuple[int, int],
        band_shape: tuple[int, int],
        dft: bool,
        planner: Planner,
        wisdom_path: Path | None,
        out_rows: int,
        constants: KernelConstants,
    ) -> None:
        self.batches = batches
        self.threads = min(threads, len(batches))
        self.constants = constants
        #: Whether a worker waits for a pass's gate spinning (each thread has
        #: a CPU of its own) or in Python (see _run_worker).
        self.spin = self.threads <= available_cores()
        # Each thread's work arrays hold the largest batch; the plans of the
        # smaller batches are made on their first blocks.
        sizes = sorted({b.stop - b.start for b in batches}, reverse=True)
        ey = block_shape[0]

        def make(size: int, share: BatchedRealFFT | None) -> BatchedRealFFT:
            return BatchedRealFFT(
                size, block_shape, threads=1, planner=planner, wisdom_path=wisdom_path,
                out_rows=out_rows, share=share, strip_rows=size * ey,
            )  # fmt: skip

        works: list[ThreadWork] = []
        #: Every thread's plans, kept alive as long as the records using them.
        self._ffts: list[list[BatchedRealFFT]] = []
        for _ in range(self.threads):
            # 64-byte aligned on every thread, so that the compiled sums over
            # it take the same order whichever thread measures a batch (their
            # vectorised loops depend on the address's alignment).
            band = _aligned_zeros((sizes[0] if dft else 0, *band_shape)).view(np.float32)
            first = make(sizes[0], None)
            ffts = [first, *(make(size, first) for size in sizes[1:])]
            works.append(thread_work(ffts, band))
            self._ffts.append(ffts)
        #: Each thread's :class:`ThreadWork`.
        self.work: tuple[ThreadWork, ...] = tuple(works)
        #: The batches and their sizes' plans, as the compiled pass takes them.
        self.table = BatchTable(
            starts=np.array([b.start for b in batches], dtype=np.intp),
            stops=np.array([b.stop for b in batches], dtype=np.intp),
            kinds=np.array([sizes.index(b.stop - b.start) for b in batches], dtype=np.intp),
        )

    def each_batch(self, work: Callable[[slice, ThreadWork, int], None]) -> None:
        """``work(blocks, arrays, kind)`` for every batch of blocks, from
        Python, on the threads, each with its own work arrays and the plans
        of the batch's size ``arrays.plans[kind]``."""
        batches = self.batches
        order = itertools.count()  # next() is atomic: it holds the GIL

        def run(t: int) -> None:
            arrays = self.work[t]
            while (i := next(order)) < len(batches):
                work(batches[i], arrays, int(self.table.kinds[i]))

        futures: list[Future[None]] = []
        if self.threads > 1:
            pool = _worker_pool(self.threads - 1)
            futures = [pool.submit(run, t) for t in range(1, self.threads)]
        try:
            run(0)
        finally:
            # The workers write into shared arrays: never return (or raise)
            # while one is still running.
            wait(futures)
        join(futures)  # a worker's exception

    def start(self, run: PassRun, complete: Callable[[], None] | None = None) -> None:
        """Start ``run`` on the workers (:func:`measure_batches`, one call
        each, without the GIL), which take batches once its gate opens; the
        calling thread joins in :meth:`finish`. ``complete`` (the calling
        thread's part of the gradient image and its check) runs before the
        gate opens; if it raises, no batch is taken and the exception
        propagates once the workers have stopped."""
        started = False
        try:
            if self.threads > 1:
                pool = _worker_pool(self.threads - 1)
                for t in range(1, self.threads):
                    run.workers.append(pool.submit(self._run_worker, run, t))
            if complete is not None:
                complete()
            started = True
        finally:
            # Whatever happened, the gate opens: a worker waits for it.
            if not started:
                run.close_batches(len(self.batches))  # no batch is to be taken
            run.open()
            if not started:
                wait(run.workers)

    def finish(self, run: PassRun) -> None:
        """The calling thread takes batches of ``run`` until none is left and
        waits for the workers; a worker's exception is raised here."""
        try:
            self._batches_of(run, 0)
        finally:
            # The workers write into shared arrays: never return (or raise)
            # while one is still running.
            join(run.workers)

    def abandon(self, run: PassRun) -> list[BaseException]:
        """Let no thread take a further batch of ``run``; wait for its
        workers and return their exceptions."""
        run.close_batches(len(self.batches))
        return wait(run.workers)

    def _batches_of(self, run: PassRun, t: int, spins: int = 0) -> bool:
        """Thread ``t``'s share of ``run`` (see :func:`measure_batches`):
        False if its gate stayed closed for ``spins`` reads."""
        done = measure_batches(
            run.counter, run.gate, spins, self.table, self.work[t], run.frame, self.constants
        )
        return bool(done)

    def _run_worker(self, run: PassRun, t: int) -> None:
        if t == 1 and run.tail is not None:
            run.tail.run(run.frame.cur.grad)
        # With a CPU per thread, the worker waits for the gate spinning inside
        # the compiled call: a Python wait would need the GIL back once the
        # gate opens, which the calling thread holds while it places a frame
        # (up to the 5 ms switch interval). With fewer CPUs a spinning worker
        # would take the calling thread's CPU while it completes the gradient;
        # and a gate that stays closed longer (a slow check, a busy machine)
        # is waited for in Python after GATE_SPINS reads.
        if self.spin and self._batches_of(run, t, GATE_SPINS):
            return
        run.opened.wait()
        self._batches_of(run, t)


@dataclass(eq=False)
class PassRun:
    """A block pass on the threads: its arrays, the threads' shared batch
    counter and gate, its workers, and the rows of the gradient image a
    worker computes."""

    #: What the compiled pass reads and writes (:func:`measure_batches`).
    frame: PassArrays
    #: The next batch to take.
    counter: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    #: The rows of the gradient image the first worker computes (see
    #: BlockEngine._split_gradient).
    tail: GradientTail | None = None
    #: Set to 1 once the gradient image is complete and checked: workers may
    #: then take batches (see :func:`measure_batches`); ``opened`` is set
    #: with it, for workers that wait in Python.
    gate: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    opened: threading.Event = field(default_factory=threading.Event)
    workers: list[Future[None]] = field(default_factory=list)

    def open(self) -> None:
        """Let the workers take batches (see :attr:`gate`), once everything
        this thread wrote before is visible to them."""
        publish(self.gate, 0, 1)
        self.opened.set()

    def close_batches(self, n_batches: int) -> None:
        """Let no thread take a further batch, and open the gate."""
        publish(self.counter, 0, n_batches)
        self.open()


class GradientTail:
    """The rows ``split:`` of a new frame's gradient image, computed by a
    worker while the calling thread computes the rows above: their
    :class:`FrameStats`, or the exception that stopped them."""

    def __init__(self, heights: npt.NDArray[np.floating], split: int) -> None:
        self.heights = heights
        self.split = split
        self._claim = threading.Lock()
        self._done = threading.Event()
        self._stats: FrameStats | None = None
        self._error: BaseException | None = None

    def run(self, grad: F32) -> None:
        """Compute the rows into ``grad``, unless another thread has begun."""
        if not self._claim.acquire(blocking=False):
            return
        try:
            self._stats = gradient_and_stats(
                self.heights[self.split :], "x", out=grad[self.split :]
            )[1]
        except BaseException as err:
            self._error = err
        finally:
            self._done.set()

    def complete(self, grad: F32) -> FrameStats:
        """The calling thread's part: the rows above ``split``, and the
        rows below too if no worker has begun them; the whole image's stats."""
        _, head = gradient_and_stats(self.heights[: self.split], "x", out=grad[: self.split])
        self.run(grad)
        tail = self.result()
        return FrameStats(
            finite=head.finite and tail.finite,
            nonzero=head.nonzero + tail.nonzero,
            uniform=head.uniform and tail.uniform and bool(grad[0, 0] == grad[self.split, 0]),
        )

    def result(self) -> FrameStats:
        """Wait for the rows; their stats, or raise what stopped them."""
        self._done.wait()
        if self._error is not None:
            raise self._error
        assert self._stats is not None
        return self._stats


def wait(workers: list[Future[None]]) -> list[BaseException]:
    """Wait for every worker; return their exceptions."""
    return [e for e in (f.exception() for f in workers) if e is not None]


def join(workers: list[Future[None]]) -> None:
    """Wait for every worker; then raise the first one's exception, if any."""
    errors = wait(workers)
    if errors:
        raise errors[0]


def _aligned_zeros(shape: tuple[int, ...]) -> npt.NDArray[np.complex64]:
    """Zeros (complex64) at a 64-byte aligned address."""
    raw = np.zeros(int(np.prod(shape)) * 8 + 64, dtype=np.uint8)
    start = -raw.ctypes.data % 64
    return raw[start : start + int(np.prod(shape)) * 8].view(np.complex64).reshape(shape)

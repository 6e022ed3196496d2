"""A block pass (Numba, no GIL): the window placement, one thread's share of
the batches with every step (FFTs included) in one compiled call, and the
assembly of the block vectors; with the records they take.

Results do not depend on the thread count: every block is computed on its
own, in a fixed order, and the split into batches is fixed by the frame
layout.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.registration._fftw import BatchedRealFFT
from afmdrift.registration._intrinsics import atomic_load, fetch_add, fftw_execute
from afmdrift.registration._jit import jit
from afmdrift.registration._kernels import masked_medians
from afmdrift.registration._peaks import pick_peaks
from afmdrift.registration._spectra import forward_strips, normalise_cross
from afmdrift.registration._subpixel import dft_subpixel, subpixel_3pt

__all__ = [
    "BatchTable",
    "BlockVectors",
    "PassArrays",
    "Peaks",
    "Placement",
    "ThreadWork",
    "Windows",
    "assemble",
    "measure_batches",
    "place_windows",
    "thread_work",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]
U64 = npt.NDArray[np.uint64]


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

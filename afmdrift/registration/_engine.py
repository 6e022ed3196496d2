"""Per-block phase correlation on batched FFTs (the engine behind
:func:`~afmdrift.registration.measure_drift` and
:class:`~afmdrift.registration.DriftTracker`).

For one frame shape and configuration a :class:`BlockEngine` holds the block
layout, the window, the FFTW plans and every work array, so that registering
a new frame against cached reference spectra costs one forward and one
inverse batched FFT plus a few passes over the spectra.

Sign convention: a feature at ``u`` in the reference appears at ``u + d`` in
the current frame; the correlation ``irfft2(Ĉ · conj(R̂))`` then peaks at
``+d``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import os
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.errors import InputError
from afmdrift.registration import _kernels
from afmdrift.registration._blocks import (
    BlockLayout,
    FrameStats,
    Gradient,
    compiled_gradient,
    gradient_and_stats,
    gradient_image,
    gradient_offset_px,
    gradient_shape,
    raised_cosine,
    raised_cosine_axis,
)
from afmdrift.registration._fftw import (
    BatchedRealFFT,
    fftwf,
    resolve_wisdom_path,
)

__all__ = ["BlockEngine", "BlockMeasurement", "ReferenceSpectra"]

_log = logging.getLogger(__name__)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]

#: Candidate peaks lower than this fraction of a block's highest peak are
#: not verified: at low SNR their MSE is as noisy as the right one's and would
#: only add wrong picks.
CANDIDATE_RATIO = 0.7
#: Absolute floor of the spectrum magnitude (its reciprocal, 1e30, is finite
#: in float32; any textured block's spectrum is many orders above it).
_MAG_FLOOR = 1e-30
#: Largest window response (see BlockEngine.calibrate) that is still
#: corrected: a block is corrected only if no direction of true shift reads
#: as less than ``1 − MAX_RESPONSE`` of itself (the smallest singular value of
#: ``I − B``), so the correction at most doubles the block's noise. A straight
#: edge reads nothing along itself (the aperture problem): such a block is
#: left as it is.
MAX_RESPONSE = 0.5
#: Half-size of the neighbourhood suppressed around each accepted peak (px).
NMS_RADIUS = 2
#: Blocks per batch, the engine's unit of work: a batch goes through every
#: pass (window, forward FFT, normalisation, inverse FFT, peaks, sub-pixel)
#: before the next starts, so its work arrays (about 1 MB for 8 blocks of
#: 128²) stay near the core instead of streaming the whole block stack
#: through memory once per pass. The engine's threads take the batches in
#: turn (see BlockEngine), so a thread on a slower core simply does fewer
#: (virtual CPUs can differ in speed from minute to minute, and a fixed half
#: of the blocks on the slower one would set the frame's time). The last
#: ``2 * BATCH_BLOCKS`` blocks go in half batches, so that the threads end
#: closer together and neither waits long for the other's last batch
#: (figures in benchmarks/RESULTS.md). The split into batches depends only
#: on the layout (:func:`batch_split`).
BATCH_BLOCKS = 8
#: Reads of a pass's gate before a worker that spins on it waits in Python
#: instead (about 0.3 ms at 0.6 ns per read here; the gate usually opens
#: within 0.1 ms of the worker reaching it, once the calling thread has
#: completed and checked the gradient image).
GATE_SPINS = 500_000
#: Window area (px²) for which a batch holds BATCH_BLOCKS blocks; smaller
#: windows go in proportionally larger batches (the same work arrays' size),
#: so that per-batch call overhead stays small against the arithmetic.
BATCH_WINDOW_PX2 = 128 * 128

_pool_lock = threading.Lock()
_pools: dict[int, ThreadPoolExecutor] = {}
#: Engines that started a pass ahead (see BlockEngine.measure_ahead).
_ahead_engines: weakref.WeakSet[BlockEngine] = weakref.WeakSet()


def _forget_pools_after_fork() -> None:
    # A forked child has none of the parent's worker threads: a pool taken
    # over from the parent would queue work that never runs, and a pass it
    # had started ahead would never end.
    global _pool_lock
    _pool_lock = threading.Lock()
    _pools.clear()
    for engine in list(_ahead_engines):
        engine._ahead = None
    _ahead_engines.clear()


os.register_at_fork(after_in_child=_forget_pools_after_fork)


def _cpus_available() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


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


@dataclass(frozen=True)
class ReferenceSpectra:
    """Cached reference: its gradient image, window positions, the
    conjugated, magnitude-normalised block spectra times the phase ramp
    (interleaved complex in int16 fixed point, see
    :func:`afmdrift.registration._kernels.normalise_reference`) and their
    magnitudes in the sub-pixel band. ``derived`` keeps what is computed
    from the reference once and reused for every frame measured against it
    (the blocks with texture, :func:`afmdrift.registration._measure.textured_blocks`;
    whether it repeats itself, :func:`afmdrift.registration._measure.reference_repeats`)."""

    grad: F32
    top: IArr
    left: IArr
    conj_spectra: npt.NDArray[np.int16]
    band_mag: F32
    #: Per block, the inverse of ``I − B`` (n, 2, 2), ``B`` the block's
    #: measured response to its content moving under its window (see
    #: :meth:`BlockEngine.calibrate`); identity where not calibrated.
    unbias: F64
    #: Per block, the centre of its correlation weight ``(x, y)``, reference
    #: px (:func:`afmdrift.registration._kernels.weight_centroids`).
    weight_centres_px: F64
    derived: dict[str, npt.NDArray[Any]] = field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class BlockMeasurement:
    """Per-block result, all arrays of length ``n`` blocks.

    ``vectors_px[:, 0]`` is x, ``[:, 1]`` is y. ``measured`` is False for
    blocks whose window left the overlap or whose peak was unusable;
    ``placed`` is False where the window had to be clamped into the image,
    ``in_overlap`` where it had to be clamped by more than half the search
    radius (see :meth:`BlockEngine.positions_for`).
    """

    centres_px: F64
    vectors_px: F64
    confidence: F64
    mse: F64
    measured: BArr
    placed: BArr
    in_overlap: BArr
    #: Where each block's vector applies ``(x, y)``, reference px: the centre
    #: of its correlation weight (``ReferenceSpectra.weight_centres_px``).
    weight_centres_px: F64
    #: Number of measured blocks and the per-axis median ``(x, y)`` of their
    #: vectors (NaN if none).
    n_measured: int
    median_px: tuple[float, float]


@dataclass(frozen=True)
class _Work:
    """One thread's FFT plans and work arrays for batches of one size.

    ``band`` receives the weighted cross-power band of the ``dft`` sub-pixel
    step (interleaved complex; no blocks for the other methods)."""

    fft: BatchedRealFFT
    band: F32


@dataclass
class _Peaks:
    """Per-block integer peak, sub-pixel offset and checks (all blocks; each
    batch writes its slice)."""

    sy: IArr
    sx: IArr
    fy: F64
    fx: F64
    ok: BArr
    peak: F32
    mse: F64

    @classmethod
    def empty(cls, n: int) -> _Peaks:
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


class BlockEngine:
    """Layout, window, FFT plans and work arrays for one frame shape.

    The blocks are processed in batches of :func:`batch_blocks` (:data:`BATCH_BLOCKS`
    of 128² windows); a measuring pass takes them column by column, so that
    a batch's windows share their row transforms
    (:func:`_kernels.forward_strips`). With
    ``config.threads > 1`` the calling thread and pool workers take the
    batches in turn, each with its own single-threaded FFTW plans and work
    arrays: a thread's share of a measuring pass is one compiled call that
    runs the FFTs itself and holds no GIL (:func:`_kernels.measure_batches`);
    :meth:`measure_ahead` starts a frame's pass before it is asked for. Every batch is
    computed on its own (its blocks and order depend only on the layout), with plans
    of the same size (which FFTW's wisdom
    makes the same algorithm), so which thread does which batch never
    changes the results.

    Not thread-safe: use one engine per calling thread.

    Parameters
    ----------
    image_shape : (int, int)
        ``(rows, cols)`` of the height images (each ≥ 64).
    config : RegistrationConfig
    """

    def __init__(self, image_shape: tuple[int, int], config: RegistrationConfig) -> None:
        if config.gradient == "auto":
            raise ValueError(
                "BlockEngine needs a concrete gradient; resolve gradient='auto' for the "
                "reference image with config_for_image"
            )
        self.image_shape = image_shape
        self.config = config
        #: The pre-filter of eq. (2) (``config.gradient``, never ``"auto"``).
        self.prefilter: Gradient = config.gradient
        self.layout = BlockLayout.build(
            gradient_shape(image_shape, self.prefilter),
            extended_size=config.extended_size,
            block_size=config.block_size,
            max_shift_px=config.max_shift_px,
        )
        lay = self.layout
        n = lay.n_blocks
        ey, ex = lay.ext
        self.window = raised_cosine(ey, ex)
        # Its two factors, for the measuring pass's forward transform.
        self._wy: F32 = raised_cosine_axis(ey).astype(np.float32)
        self._wx: F32 = raised_cosine_axis(ex).astype(np.float32)
        # Low-frequency band of the cross-power spectrum used by the "dft"
        # sub-pixel method (rfft layout: all ky in the band, kx >= 0).
        ky_max = max(1, int(config.subpixel_band * ey / 2))
        kx_max = max(1, int(config.subpixel_band * ex / 2))
        band_shape = (2 * ky_max + 1, kx_max + 1)
        self._fy = np.arange(-ky_max, ky_max + 1) / ey
        self._fx = np.arange(0, kx_max + 1) / ex
        wisdom = resolve_wisdom_path(config.fftw_wisdom)
        self._batches = batch_split(n, batch_blocks(lay.ext))
        # Batches take the blocks column by column, so that the blocks of a
        # batch share their windows' columns and rows
        # (_kernels.forward_strips).
        self._order: IArr = np.lexsort((lay.top, lay.left)).astype(np.intp)
        self._threads = min(config.threads, len(self._batches))
        #: Whether a worker waits for a pass's gate spinning (each thread has
        #: a CPU of its own) or in Python (see _run_worker).
        self._spin = self._threads <= _cpus_available()
        dft = config.subpixel == "dft"
        # Each thread's work arrays hold the largest batch; the plans of the
        # smaller batches are made on their first blocks.
        sizes = sorted({b.stop - b.start for b in self._batches}, reverse=True)

        def thread_work() -> dict[int, _Work]:
            # 64-byte aligned on every thread, so that the compiled sums over
            # it take the same order whichever thread measures a batch (their
            # vectorised loops depend on the address's alignment).
            band = _aligned_zeros((sizes[0] if dft else 0, *band_shape)).view(np.float32)
            works: dict[int, _Work] = {}
            for size in sizes:
                works[size] = _Work(
                    fft=BatchedRealFFT(
                        size,
                        (ey, ex),
                        threads=1,
                        planner=config.fftw_planner,
                        wisdom_path=wisdom,
                        out_rows=2 * lay.max_shift[0] + 1,
                        share=works[sizes[0]].fft if works else None,
                        strip_rows=size * ey,
                    ),
                    band=band[:size] if dft else band,
                )
            return works

        self._work: tuple[dict[int, _Work], ...] = tuple(
            thread_work() for _ in range(self._threads)
        )
        # What each thread passes to the compiled pass (measure_batches): the
        # batches, their sizes' plans, its work arrays.
        self._batch_table = (
            np.array([b.start for b in self._batches], dtype=np.intp),
            np.array([b.stop for b in self._batches], dtype=np.intp),
            np.array([sizes.index(b.stop - b.start) for b in self._batches], dtype=np.intp),
        )
        fftw = fftwf()
        self._execute = np.array(
            [fftw.execute_r2c, fftw.execute_c2c, fftw.execute_c2r], dtype=np.uint64
        )
        self._thread_args: tuple[tuple[object, ...], ...] = tuple(
            (
                np.stack([work[size].fft.plans for size in sizes]),
                work[sizes[0]].fft.pointers,
                work[sizes[0]].fft.spectrum.view(np.float32),
                work[sizes[0]].fft.out,
                work[sizes[0]].band,
                work[sizes[0]].fft.strip,
                work[sizes[0]].fft.strip_spectrum.view(np.float32),
                np.empty(sizes[0], dtype=np.intp),
            )
            for work in self._work
        )
        self._subpixel_code = _kernels.SUBPIXEL_CODES[config.subpixel]
        #: A pass started ahead of its frame's measure call (see measure_ahead).
        self._ahead: _Pass | None = None
        # The periodic raised cosine has a DFT with only a few non-zero terms;
        # removing the window-weighted block mean is a subtraction on them.
        wspec = np.fft.rfft2(self.window.astype(np.float64))
        nz = np.abs(wspec) > 1e-9 * abs(wspec[0, 0])
        w_rows, w_cols = (a.astype(np.intp) for a in np.nonzero(nz))
        # The arguments both normalisation kernels start with: the window's
        # non-zero DFT terms (rows, columns, values as (re, im)) and their sum
        # for the mean removal, the magnitude floor, the sub-pixel band.
        self._spectrum_args: tuple[IArr, IArr, F32, float, float, float, int, int] = (
            w_rows,
            w_cols,
            np.column_stack([wspec[nz].real, wspec[nz].imag]).astype(np.float32),
            float(wspec[0, 0].real),
            config.eps_rel,
            _MAG_FLOOR,
            ky_max,
            kx_max,
        )
        stride = config.mse_stride_px
        by, bx = lay.block
        self._mse_rows = np.arange(0, by, stride, dtype=np.intp)
        self._mse_cols = np.arange(0, bx, stride, dtype=np.intp)
        self._inner = np.array([(ey - by) // 2, (ex - bx) // 2], dtype=np.intp)
        # Block centres (x, y) in image pixels: references always have their
        # windows at the grid positions (see reference, current_as_reference).
        off_x, off_y = gradient_offset_px(self.prefilter)
        self._centres: F64 = np.column_stack(
            [lay.left + off_x + (ex - 1) / 2.0, lay.top + off_y + (ey - 1) / 2.0]
        ).astype(np.float64)
        self._centres.flags.writeable = False
        # The inverse FFT's scale: correlation peak of identical blocks.
        self._area = float(ey * ex)
        scratch_top, scratch_left = np.empty((2, n), dtype=np.intp)
        scratch_placed, scratch_near = np.empty((2, n), dtype=bool)
        self._place_scratch = (scratch_top, scratch_left, scratch_placed, scratch_near)
        # Reference spectra: interleaved complex in int16 fixed point.
        self._fixed_shape = (n, ey, 2 * (ex // 2 + 1))
        # Normalised spectra of the last measured frame, kept only when every
        # accepted frame becomes the reference (consecutive mode); |S| in the
        # sub-pixel band is always kept (small).
        self._current: npt.NDArray[np.int16] | None = (
            np.empty(self._fixed_shape, np.int16) if config.reference == "consecutive" else None
        )
        self._no_spectra: npt.NDArray[np.int16] = np.empty((0, 1, 2), np.int16)
        # Phase ramp exp(-2πi k·m) folded into the reference spectra: every
        # correlation comes out shifted by the search radius m, so shifts
        # -m..m are rows and columns 0..2m of the (pruned) inverse FFT.
        my, mx = lay.max_shift
        ky_idx = np.arange(ey)[:, None]
        kx_idx = np.arange(ex // 2 + 1)[None, :]
        ramp = np.exp(-2j * np.pi * (ky_idx * my / ey + kx_idx * mx / ex))
        self._ramp: F32 = ramp.astype(np.complex64).view(np.float32)
        self._ramp_shift = np.array([my, mx], dtype=np.intp)
        self._cur_band_mag: F32 = np.zeros((n, *band_shape), dtype=np.float32)
        self._identity: F64 = np.tile(np.eye(2), (n, 1, 1))
        self._identity.setflags(write=False)
        # Curvature κ of the window autocorrelation A(s) = Σ w(x) w(x+s) / Σ w²
        # near s = 0 (per axis): the correlation of windowed blocks is about
        # A(p)·C(p - d), so its maximum is pulled towards p = 0 unless A is
        # divided out.
        wy = self.window.sum(axis=1).astype(np.float64)
        wx = self.window.sum(axis=0).astype(np.float64)
        self._envelope = np.array(
            [
                np.sum(np.diff(wy) ** 2) / np.sum(wy**2),
                np.sum(np.diff(wx) ** 2) / np.sum(wx**2),
            ]
        )

    @property
    def n_batches(self) -> int:
        """Number of block batches (the unit of work of the engine's threads)."""
        return len(self._batches)

    def _each_batch(self, work: Callable[[slice, _Work], None]) -> None:
        """``work(blocks, arrays)`` for every batch of blocks, from Python; on
        ``threads`` threads (the caller's among them) that take the batches in
        turn, each with its own work arrays (the reference spectra; a
        measuring pass is one compiled call per thread, see :meth:`_start`)."""
        self._drop_ahead()
        batches = self._batches
        order = itertools.count()  # next() is atomic: it holds the GIL

        def run(t: int) -> None:
            arrays = self._work[t]
            while (i := next(order)) < len(batches):
                sl = batches[i]
                work(sl, arrays[sl.stop - sl.start])

        futures: list[Future[None]] = []
        if self._threads > 1:
            pool = _worker_pool(self._threads - 1)
            futures = [pool.submit(run, t) for t in range(1, self._threads)]
        try:
            run(0)
        finally:
            # The workers write into shared arrays: never return (or raise)
            # while one is still running.
            _wait(futures)
        _join(futures)  # a worker's exception

    def prepare(
        self, heights: npt.NDArray[np.floating], *, out: F32 | None = None
    ) -> tuple[F32, FrameStats]:
        """Gradient image of ``heights`` (written into ``out`` if given) and the
        :class:`~afmdrift.registration._blocks.FrameStats` the frame checks
        need, in one pass where compiled (see
        :func:`~afmdrift.registration._blocks.gradient_and_stats`)."""
        if out is not None:
            self._drop_ahead()  # its workers may read this buffer
        return gradient_and_stats(heights, self.prefilter, out=out)

    def _split_gradient(self, heights: npt.NDArray[np.floating]) -> int:
        """Row at which a new frame's gradient image is split between the
        calling thread (rows above) and the first worker (rows from it), or
        0 for no split: one thread, or a pre-filter without the compiled
        row-wise pass. A measuring pass takes the blocks column by column,
        so its first batch reads nearly every row: the workers start on the
        batches only once the whole image and its checks are done, and
        two threads get there in about half the time."""
        if self._threads <= 1 or not compiled_gradient(heights, self.prefilter):
            return 0
        return int(heights.shape[0]) // 2

    # -- spectra ---------------------------------------------------------------

    def gradient(self, heights: npt.NDArray[np.floating], *, out: F32 | None = None) -> F32:
        """Gradient image of ``heights`` per the configured mode (float32),
        written into ``out`` if given."""
        return gradient_image(heights, self.prefilter, out=out)

    def _forward(self, blocks: IArr, fft: BatchedRealFFT, grad: F32, top: IArr, left: IArr) -> None:
        """Spectra of the windows at ``(top, left)`` (full-layout arrays) of
        ``blocks`` into ``fft.spectrum``, as a measuring pass computes them
        (:func:`_kernels.forward_strips`)."""
        _kernels.forward_strips(
            grad, top, left, blocks, self._wy, self._wx, self._execute, fft.plans, fft.pointers,
            fft.strip, fft.strip_spectrum.view(np.float32), fft.spectrum.view(np.float32),
            np.empty(blocks.size, dtype=np.intp),
        )  # fmt: skip

    @functools.cached_property
    def block_rows_px(self) -> F64:
        """Distinct rows of the block centres of the reference grid, px (sorted)."""
        rows = np.unique(np.asarray(self._centres[:, 1], dtype=np.float64))
        rows.setflags(write=False)
        return rows

    @property
    def centres_px(self) -> F64:
        """Block centres ``(x, y)`` of the reference grid, px, shape (n, 2)."""
        return self._centres

    def grid_positions(self) -> tuple[IArr, IArr]:
        """Window corners ``(top, left)`` of the layout (reference positions)."""
        return self.layout.top, self.layout.left

    def reference(self, grad: F32) -> ReferenceSpectra:
        """Spectra of a new reference at the layout's grid positions: each
        block's window-weighted mean removed, normalised to ``S / (|S| + a)``
        (``a = max(eps_rel · max|S|, 1e-30)``), conjugated, times the phase
        ramp, in int16 fixed point; with each block's weight centre and
        window response (:meth:`calibrate`)."""
        top, left = self.grid_positions()
        spectra = np.empty(self._fixed_shape, np.int16)
        band_mag = np.empty_like(self._cur_band_mag)

        def work(sl: slice, arrays: _Work) -> None:
            blocks = self._order[sl]
            self._forward(blocks, arrays.fft, grad, top, left)
            _kernels.normalise_reference(
                blocks,
                arrays.fft.spectrum.view(np.float32)[: blocks.size],
                *self._spectrum_args,
                self._ramp,
                spectra,
                band_mag,
            )

        self._each_batch(work)
        return self._completed(grad, top, left, spectra, band_mag)

    def current_as_reference(self, grad: F32, top: IArr, left: IArr) -> ReferenceSpectra:
        """The frame of the last :meth:`measure` call (gradient ``grad``,
        windows at the grid positions ``top``, ``left``) as a reference.

        In consecutive mode its normalised spectra were kept by :meth:`measure`
        and are reused (no FFT); otherwise they are computed again,
        identically, by :meth:`reference`.
        """
        self._drop_ahead()  # it would write the spectra kept here
        if self._current is None:
            return self.reference(grad)
        spectra = self._current  # already conjugated and ramped
        self._current = np.empty_like(spectra)
        return self._completed(grad, top, left, spectra, self._cur_band_mag.copy())

    def _completed(
        self, grad: F32, top: IArr, left: IArr, spectra: npt.NDArray[np.int16], band_mag: F32
    ) -> ReferenceSpectra:
        """A reference from its spectra: each block's weight centre
        (:func:`afmdrift.registration._kernels.weight_centroids`) and window
        response (:meth:`calibrate`) added."""
        offsets = np.empty((self.layout.n_blocks, 2))
        _kernels.weight_centroids(grad, top, left, self.window, offsets)
        centres = self._centres + offsets
        centres.setflags(write=False)
        ref = ReferenceSpectra(
            grad=grad,
            top=top,
            left=left,
            conj_spectra=spectra,
            band_mag=band_mag,
            unbias=self._identity,
            weight_centres_px=centres,
        )
        return self.calibrate(ref)

    def calibrate(self, ref: ReferenceSpectra) -> ReferenceSpectra:
        """``ref`` with each block's response to its content moving under its
        window measured and inverted (``unbias``).

        A block's window does not move with its content: it stays where the
        rounded prior put it, so the content of the current frame sits up
        to half a pixel off its place in the window. The correlation of the
        two windowed blocks is then weighted by the window's product at the
        content's positions, which pulls the peak towards zero shift where
        the texture is not spread evenly over the window (a particle near
        its centre on flat mica: a fifth of the offset, 0.1 px at half a
        pixel). The window's average pull is divided out in the sub-pixel
        step (:func:`afmdrift.registration._kernels.dft_subpixel`); what is
        left depends on the block's own content, so it is measured: the
        reference is registered against itself twice, with every window
        moved by 1 px towards the image's centre along x, then along y (its
        content then sits 1 px the other way under it), and the measured
        vectors (zero for an unbiased block) give the response ``B`` (2×2:
        the shift measured per pixel of true shift is ``I − B``). Measured
        vectors are corrected by ``(I − B)⁻¹`` (in :meth:`measure`). A block
        whose response is not measured or too weak to invert reliably (a
        direction of true shift read as less than ``1 − MAX_RESPONSE`` of
        itself) is left uncorrected; ``ref``'s own correction, if any, is
        replaced.

        Cost: two block passes per reference (not per frame measured
        against it). Only for the ``dft`` sub-pixel method: the 3-point
        peak models are biased by pixel locking, which is not linear in the
        shift, so a response measured at 1 px does not hold at a fraction of
        one (it made ``sinc`` 0.13 px RMS wrong on noise-free 512² particle
        frames, 0.083 px uncorrected). The reference is registered against
        itself, noise included, so its noise looks like texture spread evenly
        over the window: at low SNR the response is underestimated and the
        correction does less (it never adds a bias).
        """
        ref = dataclasses.replace(ref, unbias=self._identity)
        if self.config.subpixel != "dft" or not self.config.window_response:
            return ref
        n = self.layout.n_blocks
        resp = np.zeros((n, 2, 2))  # resp[i, :, axis]: response to a move along axis
        good = np.ones(n, dtype=bool)
        rows, cols = self.layout.grad_shape
        ey, ex = self.layout.ext
        # each window moves by one pixel towards the image's centre, so none
        # has to be clamped
        inward = (
            np.where(ref.left + ex / 2 <= cols / 2, 1, -1).astype(np.intp),
            np.where(ref.top + ey / 2 <= rows / 2, 1, -1).astype(np.intp),
        )
        for axis in (0, 1):
            step = inward[axis]
            top = ref.top + (step if axis == 1 else 0)
            left = ref.left + (step if axis == 0 else 0)
            placed = (top >= 0) & (top <= rows - ey) & (left >= 0) & (left <= cols - ex)
            meas = self._measure_windows(ref, ref.grad, top, left, placed, placed, 2.0)
            # windows moved by ±1 px: the content sits at ∓1 px under them,
            # read as ∓(I − B)·e, so the block's vector (zero if unbiased) is ±B·e
            resp[:, :, axis] = step[:, None] * meas.vectors_px
            good &= meas.measured & placed
        gain = np.eye(2) - resp  # I − B
        good &= np.isfinite(gain).all(axis=(1, 2))
        gain[~good] = np.eye(2)
        good &= np.linalg.svd(gain, compute_uv=False)[:, -1] >= 1.0 - MAX_RESPONSE
        unbias = np.tile(np.eye(2), (n, 1, 1))
        if good.any():
            unbias[good] = np.linalg.inv(gain[good])
        unbias.setflags(write=False)
        return dataclasses.replace(ref, unbias=unbias)

    # -- measurement -----------------------------------------------------------

    def positions_for(
        self, ref: ReferenceSpectra, prior_px: tuple[float, float]
    ) -> tuple[IArr, IArr, BArr, BArr]:
        """Window corners in the current frame for an expected shift ``prior_px``.

        Windows are moved by the rounded prior. A window that would leave the
        image is clamped into it; its content then sits off-centre in the
        window, where the window biases the sub-pixel estimate towards zero
        shift (by a few per cent of the offset). Such blocks are flagged
        ``placed=False`` (used only when too few placed blocks exist, e.g.
        in frames barely larger than one window) and, when clamped by more
        than half the search radius, ``near=False`` (not measured).

        Returns ``(top, left, placed, near)``.
        """
        n = self.layout.n_blocks
        top, left = np.empty((2, n), dtype=np.intp)
        placed, near = np.empty((2, n), dtype=bool)
        self._place(ref, prior_px, top, left, placed, near)
        return top, left, placed, near

    def placed_fraction(self, ref: ReferenceSpectra, prior_px: tuple[float, float]) -> float:
        """Share of the blocks whose windows :meth:`positions_for` would place
        without clamping (in the engine's scratch arrays)."""
        return self._place(ref, prior_px, *self._place_scratch) / self.layout.n_blocks

    def _place(
        self,
        ref: ReferenceSpectra,
        prior_px: tuple[float, float],
        top: IArr,
        left: IArr,
        placed: BArr,
        near: BArr,
    ) -> int:
        """:meth:`positions_for` into the given arrays; returns the placed count."""
        lay = self.layout
        ey, ex = lay.ext
        rows, cols = lay.grad_shape
        count: int = _kernels.place_windows(
            ref.top, ref.left, round(prior_px[1]), round(prior_px[0]), rows - ey, cols - ex,
            lay.max_shift[0] // 2, lay.max_shift[1] // 2, top, left, placed, near,
        )  # fmt: skip
        return count

    def measure(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        *,
        prior_px: tuple[float, float] = (0.0, 0.0),
        search_px: float | None = None,
        heights: npt.NDArray[np.floating] | None = None,
        check: Callable[[FrameStats], None] | None = None,
    ) -> tuple[BlockMeasurement, IArr, IArr]:
        """Measure every block's motion vector from ``ref`` to ``grad``.

        ``search_px`` narrows the peak search to ±``search_px`` around the
        prior (never wider than the layout's ``max_shift``).

        With ``heights``, ``grad`` is first filled with their gradient image
        (as by :meth:`prepare`) and ``check`` is called with its
        :class:`~afmdrift.registration._blocks.FrameStats`; if it raises,
        nothing is measured and the exception propagates. On several threads
        with the x gradient, a worker computes the lower half of the image
        while the calling thread computes the upper half (see
        :meth:`_split_gradient`).

        If :meth:`measure_ahead` started this very pass (the same ``ref``,
        ``grad`` and ``heights`` objects, prior and search), its result is
        used; it is the same as computing it now.

        Returns the measurement and the window corners ``(top, left)`` used in
        the current frame (so its spectra can become the next reference).
        """
        ahead = self._ahead
        if ahead is not None and ahead.matches(ref, grad, heights, prior_px, search_px):
            self._ahead = None
            return self._finish(ahead), ahead.top, ahead.left
        top, left, placed, near = self.positions_for(ref, prior_px)
        p = self._start(ref, grad, top, left, placed, near, search_px, heights, check)
        return self._finish(p), top, left

    def measure_ahead(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        *,
        prior_px: tuple[float, float],
        heights: npt.NDArray[np.floating],
        check: Callable[[FrameStats], None],
        search_px: float | None = None,
    ) -> bool:
        """Start :meth:`measure` of a frame that will be measured next, and
        return while the engine's workers go on with it (without the GIL, so
        the caller's Python runs beside them).

        The gradient image and ``check`` run now; if the check refuses the
        frame, nothing is started (the later :meth:`measure` refuses it
        again) and False is returned. The pass is completed by the
        :meth:`measure` call with the same arguments, or by
        :meth:`finish_ahead`; any other use of the engine drops it first.
        """
        top, left, placed, near = self.positions_for(ref, prior_px)
        try:
            p = self._start(ref, grad, top, left, placed, near, search_px, heights, check)
        except InputError:
            return False
        p.prior_px, p.heights = prior_px, heights
        self._ahead = p
        _ahead_engines.add(self)
        return True

    def finish_ahead(self) -> None:
        """Complete a pass started by :meth:`measure_ahead` on this thread
        too, and keep its result for the :meth:`measure` call it is for:
        afterwards no worker of this engine is running."""
        ahead = self._ahead
        if ahead is not None and ahead.result is None:
            ahead.result = self._finish(ahead)

    def _drop_ahead(self) -> None:
        """Stop and forget a pass started ahead that no call used."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead.result is None:
            ahead.close_batches(len(self._batches))
            # Its result is not wanted: a worker's error is logged here
            # rather than raised from the unrelated call that dropped it.
            for error in _wait(ahead.workers):
                _log.error("a block pass started ahead failed", exc_info=error)

    def _start(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        top: IArr,
        left: IArr,
        placed: BArr,
        near: BArr,
        search_px: float | None,
        heights: npt.NDArray[np.floating] | None,
        check: Callable[[FrameStats], None] | None,
    ) -> _Pass:
        """Start a block pass with the current frame's windows at ``(top,
        left)`` (``placed``, ``near``: see :meth:`positions_for`): the pool
        workers start on the batches (:func:`_kernels.measure_batches`, one
        call each, without the GIL); the calling thread joins in
        :meth:`_finish`. With ``heights``, the gradient image is made and
        checked here first (see :meth:`measure`)."""
        self._drop_ahead()
        my, mx = self.layout.max_shift
        if search_px is not None:
            my, mx = min(my, int(search_px)), min(mx, int(search_px))
        peaks = _Peaks.empty(self.layout.n_blocks)
        search = np.array([my, mx, *self.layout.max_shift], dtype=np.intp)
        common = (
            self._order, grad, top, left, self._wy, self._wx, *self._spectrum_args,
            ref.conj_spectra, ref.band_mag,
            self._ramp, self._no_spectra if self._current is None else self._current,
            self._cur_band_mag, search, self.config.peaks, CANDIDATE_RATIO, NMS_RADIUS, ref.grad,
            ref.top, ref.left, self._inner, self._mse_rows, self._mse_cols, self._fy, self._fx,
            self._ramp_shift, self._envelope, self._subpixel_code, self._area,
            peaks.sy, peaks.sx, peaks.peak, peaks.mse, peaks.fx, peaks.fy, peaks.ok,
        )  # fmt: skip
        p = _Pass(
            ref=ref, grad=grad, search_px=search_px, top=top, left=left, placed=placed,
            near=near, my=my, mx=mx, peaks=peaks, common=common,
        )  # fmt: skip
        if heights is not None:
            if check is None:
                raise ValueError("a new frame's heights come with their check")
            split = self._split_gradient(heights)
            if split:
                p.tail = _GradientTail(heights, split)
            else:
                # All of it, and the check, before any worker reads it.
                check(self.prepare(heights, out=grad)[1])
        started = False
        try:
            if self._threads > 1:
                pool = _worker_pool(self._threads - 1)
                for t in range(1, self._threads):
                    p.workers.append(pool.submit(self._run_worker, p, t))
            if p.tail is not None and check is not None:
                check(p.tail.complete(grad))
            started = True
        finally:
            # Whatever happened, the gate opens: a worker waits for it.
            if not started:
                p.close_batches(len(self._batches))  # no batch is to be taken
            p.open()
            if not started:
                _wait(p.workers)
        return p

    def _batches_of(self, p: _Pass, t: int, spins: int = 0) -> bool:
        """Thread ``t``'s share of pass ``p`` (see
        :func:`_kernels.measure_batches`): False if its gate stayed closed
        for ``spins`` reads."""
        done = _kernels.measure_batches(
            p.counter, p.gate, spins, *self._batch_table, self._execute, self._thread_args[t],
            p.common,
        )  # fmt: skip
        return bool(done)

    def _run_worker(self, p: _Pass, t: int) -> None:
        if t == 1 and p.tail is not None:
            p.tail.run(p.grad)
        # With a CPU per thread, the worker waits for the gate spinning inside
        # the compiled call: a Python wait would need the GIL back once the
        # gate opens, which the calling thread holds while it places a frame
        # (up to the 5 ms switch interval). With fewer CPUs a spinning worker
        # would take the calling thread's CPU while it completes the gradient;
        # and a gate that stays closed longer (a slow check, a busy machine)
        # is waited for in Python after GATE_SPINS reads.
        if self._spin and self._batches_of(p, t, GATE_SPINS):
            return
        p.opened.wait()
        self._batches_of(p, t)

    def _finish(self, p: _Pass) -> BlockMeasurement:
        """The calling thread takes batches of ``p`` until none is left,
        waits for the workers, and assembles the block vectors."""
        if p.result is not None:
            return p.result
        try:
            self._batches_of(p, 0)
        finally:
            # The workers write into shared arrays: never return (or raise)
            # while one is still running.
            _join(p.workers)
        n = self.layout.n_blocks
        peaks, my, mx, top, left, ref = p.peaks, p.my, p.mx, p.top, p.left, p.ref
        vec = np.empty((n, 2), dtype=np.float64)
        measured = np.empty(n, dtype=bool)
        confidence = np.empty(n, dtype=np.float64)
        median = np.empty(2)
        n_measured = _kernels.assemble(
            top, left, ref.top, ref.left, peaks.sy, peaks.sx, peaks.fy, peaks.fx, peaks.ok,
            peaks.mse, peaks.peak, self._area, p.near, my, mx, ref.unbias, vec, measured,
            confidence, median,
        )  # fmt: skip
        return BlockMeasurement(
            centres_px=self._centres,
            vectors_px=vec,
            confidence=confidence,
            mse=peaks.mse,
            measured=measured,
            placed=p.placed,
            in_overlap=p.near,
            weight_centres_px=ref.weight_centres_px,
            n_measured=int(n_measured),
            median_px=(float(median[0]), float(median[1])),
        )

    def _measure_windows(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        top: IArr,
        left: IArr,
        placed: BArr,
        near: BArr,
        search_px: float | None,
    ) -> BlockMeasurement:
        """:meth:`measure` with the current frame's windows at ``(top, left)``
        (``placed``, ``near``: see :meth:`positions_for`)."""
        return self._finish(self._start(ref, grad, top, left, placed, near, search_px, None, None))


def _aligned_zeros(shape: tuple[int, ...]) -> npt.NDArray[np.complex64]:
    """Zeros (complex64) at a 64-byte aligned address."""
    raw = np.zeros(int(np.prod(shape)) * 8 + 64, dtype=np.uint8)
    start = -raw.ctypes.data % 64
    return raw[start : start + int(np.prod(shape)) * 8].view(np.complex64).reshape(shape)


def _wait(workers: list[Future[None]]) -> list[BaseException]:
    """Wait for every worker; return their exceptions."""
    return [e for e in (f.exception() for f in workers) if e is not None]


def _join(workers: list[Future[None]]) -> None:
    """Wait for every worker; then raise the first one's exception, if any."""
    errors = _wait(workers)
    if errors:
        raise errors[0]


class _GradientTail:
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


@dataclass(eq=False)
class _Pass:
    """A block pass in flight: what it measures (``ref``, ``grad``, the
    frame's ``heights`` and the prior and search it was started for), its
    windows, its results, and the threads' shared batch counter."""

    ref: ReferenceSpectra
    grad: F32
    search_px: float | None
    top: IArr
    left: IArr
    placed: BArr
    near: BArr
    my: int
    mx: int
    peaks: _Peaks
    #: The arguments of measure_batches after the thread's own.
    common: tuple[object, ...]
    heights: npt.NDArray[np.floating] | None = None
    prior_px: tuple[float, float] | None = None
    #: The next batch to take.
    counter: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    #: The rows of the gradient image the first worker computes (see
    #: BlockEngine._split_gradient).
    tail: _GradientTail | None = None
    #: Set to 1 once the gradient image is complete and checked: workers may
    #: then take batches (see _kernels.measure_batches); ``opened`` is set
    #: with it, for workers that wait in Python.
    gate: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    opened: threading.Event = field(default_factory=threading.Event)
    workers: list[Future[None]] = field(default_factory=list)
    result: BlockMeasurement | None = None

    def open(self) -> None:
        """Let the workers take batches (see :attr:`gate`), once everything
        this thread wrote before is visible to them."""
        _kernels.publish(self.gate, 0, 1)
        self.opened.set()

    def close_batches(self, n_batches: int) -> None:
        """Let no thread take a further batch, and open the gate."""
        _kernels.publish(self.counter, 0, n_batches)
        self.open()

    def matches(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        heights: npt.NDArray[np.floating] | None,
        prior_px: tuple[float, float],
        search_px: float | None,
    ) -> bool:
        """Whether this is the pass :meth:`BlockEngine.measure` would compute
        for these arguments."""
        return (
            self.ref is ref
            and self.grad is grad
            and self.heights is not None
            and self.heights is heights
            and self.prior_px == prior_px
            and self.search_px == search_px
        )


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

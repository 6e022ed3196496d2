"""Per-block phase correlation on batched FFTs (the engine behind
:func:`~afmdrift.registration.measure_drift` and
:class:`~afmdrift.registration.DriftTracker`).

For one frame shape and configuration a :class:`BlockEngine` holds the block
layout, the window, the kernels' constants and its threads' FFTW plans and
work arrays (:class:`~afmdrift.registration._passes.PassThreads`), so that
registering a new frame against cached reference spectra costs one forward
and one inverse batched FFT plus a few passes over the spectra. It makes
reference spectra, calibrates each block's window response, places the
windows and measures the blocks.

Sign convention: a feature at ``u`` in the reference appears at ``u + d`` in
the current frame; the correlation ``irfft2(Ĉ · conj(R̂))`` then peaks at
``+d``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.errors import InputError
from afmdrift.registration import _passes, _spectra
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
)
from afmdrift.registration._constants import KernelConstants, kernel_constants
from afmdrift.registration._fftw import resolve_wisdom_path
from afmdrift.registration._passes import (
    BlockVectors,
    GradientTail,
    PassArrays,
    PassRun,
    PassThreads,
    Peaks,
    Placement,
    ThreadWork,
    Windows,
    batch_blocks,
    batch_split,
)

__all__ = ["BlockEngine", "BlockMeasurement", "ReferenceSpectra"]

_log = logging.getLogger(__name__)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]

#: Largest window response (see BlockEngine.calibrate) that is still
#: corrected: a block is corrected only if no direction of true shift reads
#: as less than ``1 − MAX_RESPONSE`` of itself (the smallest singular value of
#: ``I − B``), so the correction at most doubles the block's noise. A straight
#: edge reads nothing along itself (the aperture problem): such a block is
#: left as it is.
MAX_RESPONSE = 0.5
#: Engines that started a pass ahead (see BlockEngine.measure_ahead).
_ahead_engines: weakref.WeakSet[BlockEngine] = weakref.WeakSet()


def _forget_passes_after_fork() -> None:
    # A forked child has none of the parent's worker threads: a pass started
    # ahead would never end.
    for engine in list(_ahead_engines):
        engine._ahead = None
    _ahead_engines.clear()


os.register_at_fork(after_in_child=_forget_passes_after_fork)


@dataclass(frozen=True)
class ReferenceSpectra:
    """Cached reference: its gradient image, window positions, the
    conjugated, magnitude-normalised block spectra times the phase ramp
    (interleaved complex in int16 fixed point, see
    :func:`afmdrift.registration._spectra.normalise_reference`) and their
    magnitudes in the sub-pixel band. ``derived`` keeps what is computed
    from the reference once and reused for every frame measured against it
    (the blocks with texture, :func:`afmdrift.registration._measure.textured_blocks`;
    whether it repeats itself, :func:`afmdrift.registration._measure.reference_repeats`,
    and the lattice vectors the coarse alignments against it decide with)."""

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
    #: px (:func:`afmdrift.registration._spectra.weight_centroids`).
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


class BlockEngine:
    """Layout, window, FFT plans and work arrays for one frame shape.

    The blocks are processed in batches of :func:`~._passes.batch_blocks`
    (:data:`~._passes.BATCH_BLOCKS` of 128² windows); a measuring pass takes
    them column by column, so that a batch's windows share their row
    transforms (:func:`_spectra.forward_strips`). With ``config.threads > 1``
    the calling thread and pool workers take the batches in turn, each with
    its own single-threaded FFTW plans and work arrays
    (:class:`~._passes.PassThreads`): a thread's share of a measuring pass is
    one compiled call that runs the FFTs itself and holds no GIL
    (:func:`_passes.measure_batches`); :meth:`measure_ahead` starts a frame's
    pass before it is asked for. Every batch is
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
            block_search_px=config.block_search_px,
        )
        lay = self.layout
        n = lay.n_blocks
        ey, ex = lay.ext
        self.window = raised_cosine(ey, ex)
        #: The compiled kernels' constants.
        self.constants: KernelConstants = kernel_constants(lay, self.window, config)
        spectrum = self.constants.spectrum
        band_shape = (2 * spectrum.ky + 1, spectrum.kx + 1)
        self._batches = batch_split(n, batch_blocks(lay.ext))
        # Batches take the blocks column by column, so that the blocks of a
        # batch share their windows' columns and rows
        # (_spectra.forward_strips).
        self._order: IArr = np.lexsort((lay.top, lay.left)).astype(np.intp)
        self._threads = PassThreads(
            self._batches,
            threads=config.threads,
            block_shape=(ey, ex),
            band_shape=band_shape,
            dft=config.subpixel == "dft",
            planner=config.fftw_planner,
            wisdom_path=resolve_wisdom_path(config.fftw_wisdom),
            out_rows=2 * lay.max_shift[0] + 1,
            constants=self.constants,
        )
        #: A pass started ahead of its frame's measure call (see measure_ahead).
        self._ahead: _Pass | None = None
        # Block centres (x, y) in image pixels: references always have their
        # windows at the grid positions (see reference, current_as_reference).
        off_x, off_y = gradient_offset_px(self.prefilter)
        self._centres: F64 = np.column_stack(
            [lay.left + off_x + (ex - 1) / 2.0, lay.top + off_y + (ey - 1) / 2.0]
        ).astype(np.float64)
        self._centres.flags.writeable = False
        rows, cols = lay.grad_shape
        # Where windows may go: corners within these, clamped by at most
        # half the search to be measured (_passes.place_windows).
        self._bounds = (rows - ey, cols - ex, lay.max_shift[0] // 2, lay.max_shift[1] // 2)
        scratch_top, scratch_left = np.empty((2, n), dtype=np.intp)
        scratch_placed, scratch_near = np.empty((2, n), dtype=bool)
        self._place_scratch = Placement(scratch_top, scratch_left, scratch_placed, scratch_near)
        # Reference spectra: interleaved complex in int16 fixed point.
        self._fixed_shape = (n, ey, 2 * (ex // 2 + 1))
        # Normalised spectra of the last measured frame, kept only when every
        # accepted frame becomes the reference (consecutive mode); |S| in the
        # sub-pixel band is always kept (small).
        self._current: npt.NDArray[np.int16] | None = (
            np.empty(self._fixed_shape, np.int16) if config.reference == "consecutive" else None
        )
        self._no_spectra: npt.NDArray[np.int16] = np.empty((0, 1, 2), np.int16)
        self._cur_band_mag: F32 = np.zeros((n, *band_shape), dtype=np.float32)
        self._identity: F64 = np.tile(np.eye(2), (n, 1, 1))
        self._identity.setflags(write=False)

    @property
    def n_batches(self) -> int:
        """Number of block batches (the unit of work of the engine's threads)."""
        return len(self._batches)

    def _each_batch(self, work: Callable[[slice, ThreadWork, int], None]) -> None:
        """``work(blocks, arrays, kind)`` for every batch of blocks, from
        Python, on the engine's threads (:meth:`PassThreads.each_batch`: the
        reference spectra; a measuring pass is one compiled call per thread,
        see :meth:`_start`)."""
        self._drop_ahead()
        self._threads.each_batch(work)

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
        if self._threads.threads <= 1 or not compiled_gradient(heights, self.prefilter):
            return 0
        return int(heights.shape[0]) // 2

    # -- spectra ---------------------------------------------------------------

    def gradient(self, heights: npt.NDArray[np.floating], *, out: F32 | None = None) -> F32:
        """Gradient image of ``heights`` per the configured mode (float32),
        written into ``out`` if given."""
        return gradient_image(heights, self.prefilter, out=out)

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

        windows = Windows(grad, top, left)
        c = self.constants

        def work(sl: slice, arrays: ThreadWork, kind: int) -> None:
            # the forward transform as a measuring pass computes it
            blocks = self._order[sl]
            _spectra.forward_strips(c.transform, windows, blocks, arrays.plans[kind], arrays)
            _spectra.normalise_reference(
                c.spectrum, blocks, arrays.spec[: blocks.size], spectra, band_mag
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
        (:func:`afmdrift.registration._spectra.weight_centroids`) and window
        response (:meth:`calibrate`) added."""
        offsets = np.empty((self.layout.n_blocks, 2))
        _spectra.weight_centroids(grad, top, left, self.window, offsets)
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
        step (:func:`afmdrift.registration._subpixel.dft_subpixel`); what is
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
        self._place(ref, prior_px, Placement(top, left, placed, near))
        return top, left, placed, near

    def placed_fraction(self, ref: ReferenceSpectra, prior_px: tuple[float, float]) -> float:
        """Share of the blocks whose windows :meth:`positions_for` would place
        without clamping (in the engine's scratch arrays)."""
        return self._place(ref, prior_px, self._place_scratch) / self.layout.n_blocks

    def _place(self, ref: ReferenceSpectra, prior_px: tuple[float, float], out: Placement) -> int:
        """:meth:`positions_for` into ``out``; returns the placed count."""
        count: int = _passes.place_windows(
            ref.top, ref.left, round(prior_px[1]), round(prior_px[0]), self._bounds, out
        )
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
            # Its result is not wanted: a worker's error is logged here
            # rather than raised from the unrelated call that dropped it.
            for error in self._threads.abandon(ahead.run):
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
        workers start on the batches (:meth:`PassThreads.start`); the calling
        thread joins in :meth:`_finish`. With ``heights``, the gradient image
        is made and checked here first (see :meth:`measure`)."""
        self._drop_ahead()
        my, mx = self.layout.max_shift
        if search_px is not None:
            my, mx = min(my, int(search_px)), min(mx, int(search_px))
        frame = PassArrays(
            order=self._order,
            cur=Windows(grad, top, left),
            ref=Windows(ref.grad, ref.top, ref.left),
            ref_conj=ref.conj_spectra,
            ref_band_mag=ref.band_mag,
            keep=self._no_spectra if self._current is None else self._current,
            band_mag=self._cur_band_mag,
            search=np.array([my, mx, *self.layout.max_shift], dtype=np.intp),
            peaks=Peaks.empty(self.layout.n_blocks),
        )
        p = _Pass(
            ref=ref, grad=grad, search_px=search_px, top=top, left=left, placed=placed,
            near=near, run=PassRun(frame),
        )  # fmt: skip
        complete: Callable[[], None] | None = None
        if heights is not None:
            if check is None:
                raise ValueError("a new frame's heights come with their check")
            split = self._split_gradient(heights)
            if split:
                tail = p.run.tail = GradientTail(heights, split)

                def complete() -> None:
                    check(tail.complete(grad))

            else:
                # All of it, and the check, before any worker reads it.
                check(self.prepare(heights, out=grad)[1])
        self._threads.start(p.run, complete)
        return p

    def _finish(self, p: _Pass) -> BlockMeasurement:
        """The calling thread takes batches of ``p`` until none is left,
        waits for the workers, and assembles the block vectors."""
        if p.result is not None:
            return p.result
        self._threads.finish(p.run)
        n = self.layout.n_blocks
        out = BlockVectors(
            vectors=np.empty((n, 2), dtype=np.float64),
            measured=np.empty(n, dtype=bool),
            confidence=np.empty(n, dtype=np.float64),
            median=np.empty(2),
        )
        n_measured = _passes.assemble(
            p.run.frame, p.near, p.ref.unbias, self.constants.subpixel.scale, out
        )
        median = out.median
        return BlockMeasurement(
            centres_px=self._centres,
            vectors_px=out.vectors,
            confidence=out.confidence,
            mse=p.run.frame.peaks.mse,
            measured=out.measured,
            placed=p.placed,
            in_overlap=p.near,
            weight_centres_px=p.ref.weight_centres_px,
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


@dataclass(eq=False)
class _Pass:
    """A block pass in flight: what it measures (``ref``, ``grad``, the
    frame's ``heights`` and the prior and search it was started for), its
    windows, its run on the threads and its result."""

    ref: ReferenceSpectra
    grad: F32
    search_px: float | None
    top: IArr
    left: IArr
    placed: BArr
    near: BArr
    run: PassRun
    heights: npt.NDArray[np.floating] | None = None
    prior_px: tuple[float, float] | None = None
    result: BlockMeasurement | None = None

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

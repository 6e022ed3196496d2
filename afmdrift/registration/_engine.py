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

import itertools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from afmdrift.registration._blocks import (
    BlockLayout,
    gradient_image,
    gradient_offset_px,
    gradient_shape,
    raised_cosine,
)
from afmdrift.registration._config import RegistrationConfig
from afmdrift.registration._fftw import BatchedRealFFT, resolve_wisdom_path

__all__ = ["BlockEngine", "BlockMeasurement", "ReferenceSpectra"]

_Scalar = TypeVar("_Scalar", bound=np.generic)
_T = TypeVar("_T")
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]

#: Newton iterations of the ``dft`` sub-pixel method after the quadratic start
#: (quadratic convergence: the second step checks that the first converged).
_NEWTON_STEPS = 2
#: Largest Newton step (px) and the last step below which it has converged.
_MAX_STEP_PX = 1.0
_CONVERGED_PX = 0.02
#: Candidate peaks lower than this fraction of a block's highest peak are
#: not verified: at low SNR their MSE is as noisy as the right one's and would
#: only add wrong picks.
CANDIDATE_RATIO = 0.7
#: Absolute floor of the spectrum magnitude (its reciprocal, 1e30, is finite
#: in float32; any textured block's spectrum is many orders above it).
_MAG_FLOOR = 1e-30
#: Half-size of the neighbourhood suppressed around each accepted peak (px).
NMS_RADIUS = 2
#: Blocks per chunk: the block batch is split into chunks of at most this many
#: blocks (64 blocks of a 512² frame: two chunks of 32), each with its own
#: FFTW plans and work arrays. The split depends only on the layout, never on
#: the thread count, so results are bit-for-bit the same for any ``threads``.
CHUNK_BLOCKS = 32

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

    The calling thread always runs one chunk itself, so a frame split into
    ``k`` chunks on ``threads`` threads uses ``threads - 1`` pool workers.
    Chunks never submit work themselves, so sharing the pool between engines
    and calling threads cannot deadlock.
    """
    with _pool_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="afmdrift-reg")
            _pools[workers] = pool
        return pool


@dataclass(frozen=True)
class ReferenceSpectra:
    """Cached reference: its gradient image, window positions and the
    conjugated, magnitude-normalised block spectra."""

    grad: F32
    top: IArr
    left: IArr
    conj_spectra: npt.NDArray[np.complex64]
    band_mag: F32


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


@dataclass(frozen=True)
class _Chunk:
    """Blocks ``sl`` of the layout with their own FFT plans and work arrays."""

    sl: slice
    fft: BatchedRealFFT
    mag: F32
    region: F32


@dataclass(frozen=True)
class _ChunkPeaks:
    """Integer peak, sub-pixel offset and checks of one chunk's blocks."""

    sx: IArr
    sy: IArr
    fx: F64
    fy: F64
    ok: BArr
    peak: F64
    mse: F64
    band_mag: F32
    band: npt.NDArray[np.complex64] | None
    """Weighted cross-power band for the ``dft`` sub-pixel step (else None)."""


class BlockEngine:
    """Layout, window, FFT plans and work arrays for one frame shape.

    The blocks are processed in chunks of at most :data:`CHUNK_BLOCKS`, each
    with its own single-threaded FFTW plans and work arrays; with
    ``config.threads > 1`` the chunks run concurrently (pyFFTW and NumPy
    release the GIL), the calling thread taking one of them.

    Not thread-safe: use one engine per calling thread.

    Parameters
    ----------
    image_shape : (int, int)
        ``(rows, cols)`` of the height images (each ≥ 64).
    config : RegistrationConfig
    """

    def __init__(self, image_shape: tuple[int, int], config: RegistrationConfig) -> None:
        self.image_shape = image_shape
        self.config = config
        self.layout = BlockLayout.build(
            gradient_shape(image_shape, config.gradient),
            extended_size=config.extended_size,
            block_size=config.block_size,
            max_shift_px=config.max_shift_px,
        )
        lay = self.layout
        n = lay.n_blocks
        ey, ex = lay.ext
        my, mx = lay.max_shift
        self.window = raised_cosine(ey, ex)
        wisdom = resolve_wisdom_path(config.fftw_wisdom)
        n_chunks = -(-n // CHUNK_BLOCKS)
        bounds = [round(i * n / n_chunks) for i in range(n_chunks + 1)]
        chunks = []
        for a, b in itertools.pairwise(bounds):
            fft = BatchedRealFFT(
                b - a, (ey, ex), threads=1, planner=config.fftw_planner, wisdom_path=wisdom
            )
            chunks.append(
                _Chunk(
                    sl=slice(a, b),
                    fft=fft,
                    mag=np.empty(fft.spectrum.shape, dtype=np.float32),
                    region=np.empty((b - a, 2 * my + 1, 2 * mx + 1), dtype=np.float32),
                )
            )
        self._chunks: tuple[_Chunk, ...] = tuple(chunks)
        self._threads = min(config.threads, len(chunks))
        spec_shape = (n, ey, ex // 2 + 1)
        # The periodic raised cosine has a DFT with only a few non-zero terms;
        # removing the window-weighted block mean is a subtraction on them.
        wspec = np.fft.rfft2(self.window.astype(np.float64))
        nz = np.abs(wspec) > 1e-9 * abs(wspec[0, 0])
        self._w_rows, self._w_cols = (a.astype(np.intp) for a in np.nonzero(nz))
        self._w_vals = wspec[nz].astype(np.complex64)
        self._w_sum = float(wspec[0, 0].real)
        self._current: npt.NDArray[np.complex64] = np.empty(spec_shape, dtype=np.complex64)
        stride = config.mse_stride_px
        by, bx = lay.block
        self._mse_rows = np.arange(0, by, stride, dtype=np.intp)
        self._mse_cols = np.arange(0, bx, stride, dtype=np.intp)
        # Flat offsets of the sample lattice in the gradient image.
        self._lattice = (
            self._mse_rows[:, None] * lay.grad_shape[1] + self._mse_cols[None, :]
        ).ravel()
        self._inner = ((ey - by) // 2, (ex - bx) // 2)
        off_x, off_y = gradient_offset_px(config.gradient)
        self._centre_offset = (off_x + (ex - 1) / 2.0, off_y + (ey - 1) / 2.0)
        self._cur_band_mag: F32 = np.zeros((n, 1, 1), dtype=np.float32)
        # Low-frequency band of the cross-power spectrum used by the "dft"
        # sub-pixel method (rfft layout: all ky in the band, kx >= 0).
        ky_max = max(1, int(config.subpixel_band * ey / 2))
        kx_max = max(1, int(config.subpixel_band * ex / 2))
        ky = np.arange(-ky_max, ky_max + 1)
        kx = np.arange(0, kx_max + 1)
        self._band_ky = ky_max
        self._band_kx = kx_max
        self._fy = ky / ey
        self._fx = kx / ex
        # Hermitian weight: columns kx > 0 stand for themselves and -kx.
        self._band_w = np.where(kx == 0, 1.0, 2.0)[None, :]
        off5 = np.arange(-2.0, 3.0)
        self._ex5 = np.exp(2j * np.pi * self._fx[:, None] * off5[None, :]).astype(np.complex64)
        self._ey5 = np.exp(2j * np.pi * self._fy[:, None] * off5[None, :]).astype(np.complex64)
        self._fx_pow = np.stack([np.ones_like(self._fx), self._fx, self._fx**2], axis=1).astype(
            np.complex64
        )
        self._fy_pow = np.stack([np.ones_like(self._fy), self._fy, self._fy**2], axis=1)
        # Curvature κ of the window autocorrelation A(s) = Σ w(x) w(x+s) / Σ w²
        # near s = 0 (per axis): the correlation of windowed blocks is about
        # A(p)·C(p - d), so its maximum is pulled towards p = 0 unless A is
        # divided out.
        wy = self.window.sum(axis=1).astype(np.float64)
        wx = self.window.sum(axis=0).astype(np.float64)
        self._envelope = (
            float(np.sum(np.diff(wy) ** 2) / np.sum(wy**2)),
            float(np.sum(np.diff(wx) ** 2) / np.sum(wx**2)),
        )

    @property
    def n_chunks(self) -> int:
        """Number of block chunks (each with its own FFT plans)."""
        return len(self._chunks)

    def _each_chunk(self, work: Callable[[_Chunk], _T]) -> list[_T]:
        """``work(chunk)`` for every chunk, in chunk order; concurrently on
        ``threads`` threads (the caller's among them) when that is above 1."""
        chunks = self._chunks
        if self._threads <= 1:
            return [work(c) for c in chunks]
        pool = _worker_pool(self._threads - 1)
        futures: list[Future[_T]] = [pool.submit(work, c) for c in chunks[1:]]
        try:
            first = work(chunks[0])
        finally:
            # The chunks write into shared arrays: never return (or raise)
            # while one is still running.
            for f in futures:
                f.exception()
        return [first, *(f.result() for f in futures)]

    # -- spectra ---------------------------------------------------------------

    def gradient(self, heights: npt.NDArray[np.floating], *, out: F32 | None = None) -> F32:
        """Gradient image of ``heights`` per the configured mode (float32),
        written into ``out`` if given."""
        return gradient_image(heights, self.config.gradient, out=out)

    def _normalised_spectra(
        self,
        chunk: _Chunk,
        grad: F32,
        top: IArr,
        left: IArr,
        out: npt.NDArray[np.complex64],
    ) -> F32:
        """Window the chunk's blocks at ``(top, left)`` (full-layout arrays),
        remove each block's window-weighted mean, FFT, and write
        ``S / (|S| + eps·max|S|)`` to ``out[chunk]``. Returns ``|S|`` in the
        sub-pixel band, shape (chunk blocks, Ly, Lx)."""
        ey, ex = self.layout.ext
        fft = chunk.fft
        real = fft.real
        win = self.window
        a = chunk.sl.start
        for i in range(real.shape[0]):
            t, le = top[a + i], left[a + i]
            np.multiply(grad[t : t + ey, le : le + ex], win, out=real[i])
        fft.forward()
        spec = fft.spectrum
        mean = spec[:, 0, 0].real / self._w_sum
        spec[:, self._w_rows, self._w_cols] -= mean[:, None] * self._w_vals[None, :]
        mag = np.abs(spec, out=chunk.mag)
        band_mag = self._band(mag)
        peak = mag.reshape(mag.shape[0], -1).max(axis=1)
        # The floor keeps 1 / (|S| + floor) finite in float32 for blocks
        # without texture (flat windows of near-blank frames: S = 0 exactly,
        # or denormal); their normalised spectrum is then (about) zero, so
        # they give no positive correlation peak and are not measured.
        mag += np.maximum(self.config.eps_rel * peak, _MAG_FLOOR)[:, None, None]
        np.reciprocal(mag, out=mag)
        np.multiply(spec, mag, out=out[chunk.sl])
        return band_mag

    def grid_positions(self) -> tuple[IArr, IArr]:
        """Window corners ``(top, left)`` of the layout (reference positions)."""
        return self.layout.top, self.layout.left

    def reference(self, grad: F32) -> ReferenceSpectra:
        """Spectra of a new reference at the layout's grid positions."""
        top, left = self.grid_positions()
        spectra = np.empty_like(self._current)

        def work(chunk: _Chunk) -> F32:
            band = self._normalised_spectra(chunk, grad, top, left, spectra)
            np.conjugate(spectra[chunk.sl], out=spectra[chunk.sl])
            return band

        band_mag = np.concatenate(self._each_chunk(work), axis=0)
        return ReferenceSpectra(
            grad=grad, top=top, left=left, conj_spectra=spectra, band_mag=band_mag
        )

    def current_as_reference(self, grad: F32, top: IArr, left: IArr) -> ReferenceSpectra:
        """Turn the spectra of the last :meth:`measure` call into a reference
        (no FFT: the cached spectra are reused)."""
        spectra = np.conjugate(self._current)
        return ReferenceSpectra(
            grad=grad, top=top, left=left, conj_spectra=spectra, band_mag=self._cur_band_mag
        )

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
        lay = self.layout
        ey, ex = lay.ext
        rows, cols = lay.grad_shape
        py, px = round(prior_px[1]), round(prior_px[0])
        want_top = ref.top + py
        want_left = ref.left + px
        top = np.clip(want_top, 0, rows - ey)
        left = np.clip(want_left, 0, cols - ex)
        placed = (top == want_top) & (left == want_left)
        near = (np.abs(top - want_top) <= lay.max_shift[0] // 2) & (
            np.abs(left - want_left) <= lay.max_shift[1] // 2
        )
        return top, left, placed, near

    def measure(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        *,
        prior_px: tuple[float, float] = (0.0, 0.0),
        search_px: float | None = None,
    ) -> tuple[BlockMeasurement, IArr, IArr]:
        """Measure every block's motion vector from ``ref`` to ``grad``.

        ``search_px`` narrows the peak search to ±``search_px`` around the
        prior (never wider than the layout's ``max_shift``).

        Returns the measurement and the window corners ``(top, left)`` used in
        the current frame (so its spectra can become the next reference).
        """
        my, mx = self.layout.max_shift
        if search_px is not None:
            my, mx = min(my, int(search_px)), min(mx, int(search_px))
        top, left, placed, near = self.positions_for(ref, prior_px)

        def work(chunk: _Chunk) -> _ChunkPeaks:
            return self._measure_chunk(chunk, ref, grad, top, left, (my, mx))

        parts = self._each_chunk(work)
        self._cur_band_mag = np.concatenate([p.band_mag for p in parts], axis=0)
        sx = np.concatenate([p.sx for p in parts])
        sy = np.concatenate([p.sy for p in parts])
        best_mse = np.concatenate([p.mse for p in parts])
        if parts[0].band is not None:
            # The dft sub-pixel step is many small array operations that hold
            # the GIL: once over all blocks on this thread beats once per
            # chunk on competing threads (measured side by side, 2 threads:
            # 8.5 against 8.7 ms per 512² frame, identical results).
            fx, fy, ok = self._dft_peak(
                np.concatenate([p.band for p in parts if p.band is not None], axis=0), sx, sy
            )
        else:
            fx = np.concatenate([p.fx for p in parts])
            fy = np.concatenate([p.fy for p in parts])
            ok = np.concatenate([p.ok for p in parts])
        vec = np.empty((sx.size, 2), dtype=np.float64)
        vec[:, 0] = (left - ref.left) + sx + fx
        vec[:, 1] = (top - ref.top) + sy + fy
        measured = near & np.isfinite(best_mse) & ok & (np.abs(sy) < my) & (np.abs(sx) < mx)
        cx, cy = self._centre_offset
        centres = np.column_stack([ref.left + cx, ref.top + cy]).astype(np.float64)
        result = BlockMeasurement(
            centres_px=centres,
            vectors_px=vec,
            confidence=np.concatenate([p.peak for p in parts]),
            mse=np.where(np.isfinite(best_mse), best_mse, np.nan),
            measured=measured,
            placed=placed,
            in_overlap=near,
        )
        return result, top, left

    def _measure_chunk(
        self,
        chunk: _Chunk,
        ref: ReferenceSpectra,
        grad: F32,
        top: IArr,
        left: IArr,
        search: tuple[int, int],
    ) -> _ChunkPeaks:
        """Spectra, correlation, candidate peaks, MSE verification and
        sub-pixel offsets of one chunk's blocks (``top``, ``left``: window
        corners of every block in the current frame; ``search``: half-widths
        ``(y, x)`` of the peak search, at most the layout's)."""
        cfg = self.config
        sl = chunk.sl
        fft = chunk.fft
        ey, ex = self.layout.ext
        my, mx = self.layout.max_shift
        ry, rx = search
        band_mag = self._normalised_spectra(chunk, grad, top, left, self._current)
        np.multiply(self._current[sl], ref.conj_spectra[sl], out=fft.cross)
        band = None
        if cfg.subpixel == "dft":
            # Cross-power weights |S_cur||S_ref| turn the phase-only band back
            # into a matched filter: noise-only frequencies get little weight.
            band = self._band(fft.cross)
            band *= band_mag * ref.band_mag[sl]
        fft.inverse()
        corr = fft.real  # (n, ey, ex), scaled by ey·ex
        scale = 1.0 / (ey * ex)

        # Top-K peaks in the search region, with non-maximum suppression.
        region = self._search_region(corr, chunk.region)
        if (ry, rx) != (my, mx):  # a narrower search: mask the rest out
            region[:, : my - ry] = -np.inf
            region[:, my + ry + 1 :] = -np.inf
            region[:, :, : mx - rx] = -np.inf
            region[:, :, mx + rx + 1 :] = -np.inf
        n = region.shape[0]
        rows = np.arange(n, dtype=np.intp)
        hy, wx = region.shape[1:]
        flat = region.reshape(n, -1)  # a view: suppression below is seen by argmax
        k = cfg.peaks
        cand_y = np.zeros((n, k), dtype=np.intp)
        cand_x = np.zeros((n, k), dtype=np.intp)
        cand_v = np.full((n, k), -np.inf, dtype=np.float32)
        offs = np.arange(-NMS_RADIUS, NMS_RADIUS + 1)
        for j in range(k):
            idx = np.argmax(flat, axis=1)
            cand_v[:, j] = flat[rows, idx]
            iy, ix = np.divmod(idx, wx)
            cand_y[:, j] = iy - my
            cand_x[:, j] = ix - mx
            if j > 0 and not bool(np.any(cand_v[:, j] >= CANDIDATE_RATIO * cand_v[:, 0])):
                break  # lower peaks would not be verified anyway
            if j + 1 < k:
                yy = np.clip(iy[:, None] + offs, 0, hy - 1)
                xx = np.clip(ix[:, None] + offs, 0, wx - 1)
                region[rows[:, None, None], yy[:, :, None], xx[:, None, :]] = -np.inf

        # Verify each plausible candidate (positive, and at least
        # CANDIDATE_RATIO of the block's highest peak) by the MSE between the
        # two gradient blocks; the lowest MSE wins.
        plausible = np.isfinite(cand_v) & (cand_v > 0) & (cand_v >= CANDIDATE_RATIO * cand_v[:, :1])
        bi, ki = np.nonzero(plausible)
        blk = bi + sl.start
        mse = np.full((n, k), np.inf)
        mse[bi, ki] = self._candidate_mse(
            ref,
            grad,
            blk,
            (top - ref.top)[blk] + cand_y[bi, ki],
            (left - ref.left)[blk] + cand_x[bi, ki],
        )
        best = np.argmin(mse, axis=1)
        sy = cand_y[rows, best]
        sx = cand_x[rows, best]

        # Sub-pixel refinement around the chosen peak: the dft method runs
        # after the chunks, over all blocks at once (see measure).
        if band is not None:
            fx = fy = np.zeros(n)
            ok = np.ones(n, dtype=bool)
        else:
            ny = (sy[:, None] + np.array([-1, 0, 1])) % ey
            nx = (sx[:, None] + np.array([-1, 0, 1])) % ex
            nb = corr[rows[:, None, None], ny[:, :, None], nx[:, None, :]].astype(np.float64)
            fy, ok_y = _subpixel(nb[:, :, 1] * scale, cfg.subpixel)
            fx, ok_x = _subpixel(nb[:, 1, :] * scale, cfg.subpixel)
            ok = ok_x & ok_y
        return _ChunkPeaks(
            sx=sx,
            sy=sy,
            fx=fx,
            fy=fy,
            ok=ok,
            peak=cand_v[rows, best].astype(np.float64) * scale,
            mse=mse[rows, best],
            band_mag=band_mag,
            band=band,
        )

    def _band(self, spec: npt.NDArray[_Scalar]) -> npt.NDArray[_Scalar]:
        """Copy of the sub-pixel band of half-spectra ``spec``, shape
        (n, 2·ky + 1, kx + 1), rows ordered ky = -ky_max .. +ky_max."""
        ky, kx = self._band_ky, self._band_kx
        return np.concatenate([spec[:, -ky:, : kx + 1], spec[:, : ky + 1, : kx + 1]], axis=1)

    def _search_region(self, corr: F32, reg: F32) -> F32:
        """Correlation at shifts ``-max..+max`` (wrapped), shape (n, 2my+1, 2mx+1).

        Copied by four slices into the work array ``reg`` (element [my, mx]
        is shift 0).
        """
        my, mx = self.layout.max_shift
        reg[:, :my, :mx] = corr[:, -my:, -mx:]
        reg[:, :my, mx:] = corr[:, -my:, : mx + 1]
        reg[:, my:, :mx] = corr[:, : my + 1, -mx:]
        reg[:, my:, mx:] = corr[:, : my + 1, : mx + 1]
        return reg

    def _dft_peak(
        self, band: npt.NDArray[np.complex64], sx: IArr, sy: IArr
    ) -> tuple[F64, F64, BArr]:
        """Continuous maximum of the band-limited correlation surface.

        ``c(p) = Re Σ_k w_k R_k exp(2πi k·p)`` over the low-frequency band of
        the cross-power spectrum ``R``. A quadratic through ``c`` around the
        best of the 5×5 integer shifts centred on the full-band peak gives the
        start; Newton steps with the analytic gradient and Hessian of ``c``
        then converge on its maximum.
        For a pure translation ``R_k = A_k exp(-2πi k·d)`` with ``A_k ≥ 0``
        symmetric in ``k``, so the maximum lies exactly at ``d`` whatever the
        texture's spectrum: no peak-shape model, no pixel-locking bias.

        Returns the offsets ``(fx, fy)`` from the integer peak and a mask of
        the blocks where the iteration converged within 3 px of it.
        """
        n = band.shape[0]
        fy, fx = self._fy, self._fx
        two_pi_i = 2j * np.pi
        two_pi = 2.0 * np.pi
        # Centre the band on the integer peak: r0 = w · R · exp(2πi k·s)
        # (w: Hermitian weight of the half-spectrum columns).
        # complex64 is ample here (phases of at most a few radians, sums of a
        # few hundred terms) and halves the work.
        r0 = band * np.exp(two_pi_i * fy[None, :] * sy[:, None]).astype(np.complex64)[:, :, None]
        r0 *= (np.exp(two_pi_i * fx[None, :] * sx[:, None]) * self._band_w).astype(np.complex64)[
            :, None, :
        ]
        # Band-limited c at the 5×5 integer offsets around it (noise can put
        # the full-band peak a pixel or two off), by separable products
        # (stacked per block: tiny products that BLAS runs on one thread);
        # quadratic start at the best of them.
        c5 = np.matmul(self._ey5.T, np.matmul(r0, self._ex5)).real  # c5[n, y, x]
        best = np.argmax(c5.reshape(n, -1), axis=1)
        by_, bx_ = np.divmod(best, 5)
        by_ = np.clip(by_, 1, 3)
        bx_ = np.clip(bx_, 1, 3)
        d3 = np.arange(-1, 2)
        c = c5[
            np.arange(n)[:, None, None],
            (by_[:, None] + d3)[:, :, None],
            (bx_[:, None] + d3)[:, None, :],
        ]
        gx = 0.5 * (c[:, 1, 2] - c[:, 1, 0])
        gy = 0.5 * (c[:, 2, 1] - c[:, 0, 1])
        hxx = c[:, 1, 2] - 2.0 * c[:, 1, 1] + c[:, 1, 0]
        hyy = c[:, 2, 1] - 2.0 * c[:, 1, 1] + c[:, 0, 1]
        hxy = 0.25 * (c[:, 2, 2] - c[:, 2, 0] - c[:, 0, 2] + c[:, 0, 0])
        qx, qy = _ascent_step(gx, gy, hxx, hyy, hxy)
        dx = qx + (bx_ - 2)  # offset from the integer peak
        dy = qy + (by_ - 2)
        ky_env, kx_env = self._envelope
        fy_pow = self._fy_pow  # (Ly, 3): 1, fy, fy²
        step = np.full(n, np.inf)
        for _ in range(_NEWTON_STEPS):
            # t[n, y, j] = Σ_x r0 · exp(2πi fx dx) · fx^j, then the y sums
            # Σ_y t · exp(2πi fy dy) · fy^i give every moment c needs.
            ex_ = np.exp(two_pi_i * fx[None, :] * dx[:, None]).astype(np.complex64)
            t = np.matmul(r0, ex_[:, :, None] * self._fx_pow[None, :, :])  # (n, Ly, 3)
            t = t * np.exp(two_pi_i * fy[None, :] * dy[:, None])[:, :, None]
            m0 = t.sum(axis=1)  # (n, 3): Σ z, Σ z fx, Σ z fx²
            my_ = np.einsum("nyj,y->nj", t[:, :, :2], fy_pow[:, 1])  # Σ z fy, Σ z fx fy
            myy = t[:, :, 0] @ fy_pow[:, 2]  # Σ z fy²
            c0 = m0[:, 0].real
            positive = c0 > 0
            inv = 1.0 / np.where(positive, c0, 1.0)
            # Derivatives of log c plus the window-envelope correction
            # (maximise c(p) / A(p), A(p) ≈ exp(-κx px²/2 - κy py²/2)).
            gx = -two_pi * m0[:, 1].imag * inv
            gy = -two_pi * my_[:, 0].imag * inv
            hxx = -(two_pi**2) * m0[:, 2].real * inv - gx * gx + kx_env
            hyy = -(two_pi**2) * myy.real * inv - gy * gy + ky_env
            hxy = -(two_pi**2) * my_[:, 1].real * inv - gx * gy
            step_x, step_y = _ascent_step(
                gx + kx_env * (sx + dx), gy + ky_env * (sy + dy), hxx, hyy, hxy
            )
            step_x = np.where(positive, step_x, 0.0)
            step_y = np.where(positive, step_y, 0.0)
            dx = dx + step_x
            dy = dy + step_y
            step = np.where(positive, np.hypot(step_x, step_y), np.inf)
        off_x = dx
        off_y = dy
        ok = (step < _CONVERGED_PX) & (np.abs(off_x) <= 3.0) & (np.abs(off_y) <= 3.0)
        return np.where(ok, off_x, 0.0), np.where(ok, off_y, 0.0), ok

    def _candidate_mse(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        block: IArr,
        shift_y: IArr,
        shift_x: IArr,
    ) -> F64:
        """Mean squared difference of the inner blocks at candidate shifts.

        One value per (block, total integer shift) pair, shape (P,). Sampled
        on a lattice of ``mse_stride_px``; the mean difference is removed (an
        offset is not a mismatch). Samples of the shifted block outside the
        current image are left out (the overlap); fewer than a quarter of the
        samples in the overlap gives ``inf``.
        """
        rows_img, cols_img = grad.shape
        iy0, ix0 = self._inner
        y0 = ref.top[block] + iy0  # inner block corner in the reference, (P,)
        x0 = ref.left[block] + ix0
        total = self._mse_rows.size * self._mse_cols.size
        by, bx = self._mse_rows[-1], self._mse_cols[-1]
        inside = (
            (y0 + shift_y >= 0)
            & (y0 + shift_y + by < rows_img)
            & (x0 + shift_x >= 0)
            & (x0 + shift_x + bx < cols_img)
        )
        if bool(inside.all()):  # the usual case: every sample overlaps
            # One flat gather per image: corner index plus the sample lattice.
            base = (y0 * cols_img + x0)[:, None] + self._lattice
            diff = grad.reshape(-1).take(base + (shift_y * cols_img + shift_x)[:, None])
            diff -= ref.grad.reshape(-1).take(base)
            mean = diff.mean(axis=1, dtype=np.float64)
            sq = np.einsum("ps,ps->p", diff, diff, dtype=np.float64) / total
            mse: F64 = np.maximum(sq - mean * mean, 0.0)
            return mse
        ry = y0[:, None] + self._mse_rows[None, :]  # (P, Ly)
        rx = x0[:, None] + self._mse_cols[None, :]  # (P, Lx)
        cy = ry + shift_y[:, None]
        cx = rx + shift_x[:, None]
        vy = (cy >= 0) & (cy < rows_img)
        vx = (cx >= 0) & (cx < cols_img)
        np.clip(cy, 0, rows_img - 1, out=cy)
        np.clip(cx, 0, cols_img - 1, out=cx)
        diff = grad[cy[:, :, None], cx[:, None, :]]
        diff -= ref.grad[ry[:, :, None], rx[:, None, :]]
        w = (vy[:, :, None] & vx[:, None, :]).astype(np.float32)
        cnt = w.sum(axis=(1, 2), dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (diff * w).sum(axis=(1, 2), dtype=np.float64) / cnt
            sq = np.square(diff - mean[:, None, None].astype(np.float32)) * w
            mse = sq.sum(axis=(1, 2), dtype=np.float64) / cnt
        mse[cnt < 0.25 * total] = np.inf
        return mse


def _ascent_step(gx: F64, gy: F64, hxx: F64, hyy: F64, hxy: F64) -> tuple[F64, F64]:
    """Newton step towards a maximum where the Hessian is negative definite,
    else a unit gradient-ascent step; both bounded by ``_MAX_STEP_PX``."""
    det = hxx * hyy - hxy * hxy
    concave = (hxx < 0) & (det > 0)
    safe = np.where(concave, det, 1.0)
    step_x = np.where(concave, -(hyy * gx - hxy * gy) / safe, np.sign(gx))
    step_y = np.where(concave, -(hxx * gy - hxy * gx) / safe, np.sign(gy))
    return (
        np.clip(step_x, -_MAX_STEP_PX, _MAX_STEP_PX),
        np.clip(step_y, -_MAX_STEP_PX, _MAX_STEP_PX),
    )


def _subpixel(c: F64, method: str) -> tuple[F64, BArr]:
    """Sub-pixel offset of a peak from its three samples ``c[:, 0..2]``
    (left, centre, right). Returns the offset in px and a validity mask."""
    cm, c0, cp = c[:, 0], c[:, 1], c[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        if method == "sinc":
            # Foroosh, Zerubia & Berthod (2002): the phase-correlation peak of a
            # sub-pixel shift is a Dirichlet kernel, so a side sample over its
            # sum with the centre gives the offset.
            right = cp >= cm
            side = np.where(right, cp, cm)
            frac = side / (side + c0)
            frac = np.where(side > 0, frac, 0.0)
            off = np.where(right, frac, -frac)
        elif method == "parabolic":
            den = cm - 2.0 * c0 + cp
            off = np.where(den < 0, 0.5 * (cm - cp) / den, 0.0)
        else:  # gaussian
            lm, l0, lp = (np.log(np.maximum(v, 1e-12)) for v in (cm, c0, cp))
            den = lm - 2.0 * l0 + lp
            off = np.where(den < 0, 0.5 * (lm - lp) / den, 0.0)
    ok = np.isfinite(off) & (np.abs(off) <= 1.0) & (c0 > 0)
    return np.where(ok, off, 0.0), ok

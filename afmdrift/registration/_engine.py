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

from dataclasses import dataclass

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

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]
BArr = npt.NDArray[np.bool_]

#: Newton iterations of the ``dft`` sub-pixel method.
_NEWTON_STEPS = 8
#: Largest Newton step (px) and the last step below which it has converged.
_MAX_STEP_PX = 1.0
_CONVERGED_PX = 0.01
#: Half-size of the neighbourhood suppressed around each accepted peak (px).
NMS_RADIUS = 2


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
    blocks whose window left the overlap or whose peak was unusable.
    """

    centres_px: F64
    vectors_px: F64
    confidence: F64
    mse: F64
    measured: BArr


class BlockEngine:
    """Layout, window, FFT plans and work arrays for one frame shape.

    Not thread-safe: use one engine per thread.

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
        self.window = raised_cosine(ey, ex)
        self.fft = BatchedRealFFT(
            n,
            (ey, ex),
            threads=config.threads,
            planner=config.fftw_planner,
            wisdom_path=resolve_wisdom_path(config.fftw_wisdom),
        )
        spec_shape = self.fft.spectrum.shape
        # The periodic raised cosine has a DFT with only a few non-zero terms;
        # removing the window-weighted block mean is a subtraction on them.
        wspec = np.fft.rfft2(self.window.astype(np.float64))
        nz = np.abs(wspec) > 1e-9 * abs(wspec[0, 0])
        self._w_rows, self._w_cols = (a.astype(np.intp) for a in np.nonzero(nz))
        self._w_vals = wspec[nz].astype(np.complex64)
        self._w_sum = float(wspec[0, 0].real)
        self._mag: F32 = np.empty(spec_shape, dtype=np.float32)
        self._current: npt.NDArray[np.complex64] = np.empty(spec_shape, dtype=np.complex64)
        my, mx = lay.max_shift
        self._reg_rows = (np.arange(-my, my + 1) % ey).astype(np.intp)
        self._reg_cols = (np.arange(-mx, mx + 1) % ex).astype(np.intp)
        stride = config.mse_stride_px
        by, bx = lay.block
        self._mse_rows = np.arange(0, by, stride, dtype=np.intp)
        self._mse_cols = np.arange(0, bx, stride, dtype=np.intp)
        self._inner = ((ey - by) // 2, (ex - bx) // 2)
        off_x, off_y = gradient_offset_px(config.gradient)
        self._centre_offset = (off_x + (ex - 1) / 2.0, off_y + (ey - 1) / 2.0)
        self._rows = np.arange(n, dtype=np.intp)
        self._cur_band_mag: F32 = np.zeros((n, 1, 1), dtype=np.float32)
        # Low-frequency band of the cross-power spectrum used by the "dft"
        # sub-pixel method (rfft layout: all ky in the band, kx >= 0).
        ky_max = max(1, int(config.subpixel_band * ey / 2))
        kx_max = max(1, int(config.subpixel_band * ex / 2))
        ky = np.arange(-ky_max, ky_max + 1)
        kx = np.arange(0, kx_max + 1)
        self._band_rows = (ky % ey).astype(np.intp)
        self._band_cols = kx.astype(np.intp)
        self._fy = ky / ey
        self._fx = kx / ex
        # Hermitian weight: columns kx > 0 stand for themselves and -kx.
        self._band_w = np.where(kx == 0, 1.0, 2.0)[None, None, :] * np.ones((1, ky.size, 1))

    # -- spectra ---------------------------------------------------------------

    def gradient(self, heights: npt.NDArray[np.floating]) -> F32:
        """Gradient image of ``heights`` per the configured mode (float32)."""
        return gradient_image(heights, self.config.gradient)

    def _normalised_spectra(
        self, grad: F32, top: IArr, left: IArr, out: npt.NDArray[np.complex64]
    ) -> None:
        """Window the blocks at ``(top, left)``, remove each block's
        window-weighted mean, FFT, and write ``S / (|S| + eps·max|S|)`` to ``out``."""
        ey, ex = self.layout.ext
        real = self.fft.real
        win = self.window
        for i in range(top.size):
            t, le = top[i], left[i]
            np.multiply(grad[t : t + ey, le : le + ex], win, out=real[i])
        self.fft.forward()
        spec = self.fft.spectrum
        mean = spec[:, 0, 0].real / self._w_sum
        spec[:, self._w_rows, self._w_cols] -= mean[:, None] * self._w_vals[None, :]
        mag = np.abs(spec, out=self._mag)
        peak = mag.reshape(mag.shape[0], -1).max(axis=1)
        mag += (self.config.eps_rel * np.maximum(peak, np.finfo(np.float32).tiny))[:, None, None]
        np.divide(spec, mag, out=out)

    def grid_positions(self) -> tuple[IArr, IArr]:
        """Window corners ``(top, left)`` of the layout (reference positions)."""
        return self.layout.top, self.layout.left

    def reference(self, grad: F32) -> ReferenceSpectra:
        """Spectra of a new reference at the layout's grid positions."""
        top, left = self.grid_positions()
        spectra = np.empty_like(self._current)
        self._normalised_spectra(grad, top, left, spectra)
        np.conjugate(spectra, out=spectra)
        return ReferenceSpectra(
            grad=grad, top=top, left=left, conj_spectra=spectra, band_mag=self._band_mag()
        )

    def _band_mag(self) -> F32:
        """Spectrum magnitudes of the last transformed blocks in the sub-pixel band."""
        return self._mag[:, self._band_rows[:, None], self._band_cols[None, :]]

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
    ) -> tuple[IArr, IArr, BArr]:
        """Window corners in the current frame for an expected shift ``prior_px``.

        Windows are moved by the rounded prior and clamped into the image; a
        block whose clamped window is farther than the search range from where
        its content is expected is marked as outside the overlap.
        """
        lay = self.layout
        ey, ex = lay.ext
        rows, cols = lay.grad_shape
        py, px = round(prior_px[1]), round(prior_px[0])
        want_top = ref.top + py
        want_left = ref.left + px
        top = np.clip(want_top, 0, rows - ey)
        left = np.clip(want_left, 0, cols - ex)
        inside = (np.abs(top - want_top) <= lay.max_shift[0] // 2) & (
            np.abs(left - want_left) <= lay.max_shift[1] // 2
        )
        return top, left, inside

    def measure(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        *,
        prior_px: tuple[float, float] = (0.0, 0.0),
    ) -> tuple[BlockMeasurement, IArr, IArr]:
        """Measure every block's motion vector from ``ref`` to ``grad``.

        Returns the measurement and the window corners ``(top, left)`` used in
        the current frame (so its spectra can become the next reference).
        """
        lay = self.layout
        cfg = self.config
        n = lay.n_blocks
        ey, ex = lay.ext
        my, mx = lay.max_shift
        top, left, inside = self.positions_for(ref, prior_px)
        self._normalised_spectra(grad, top, left, self._current)
        np.multiply(self._current, ref.conj_spectra, out=self.fft.cross)
        band = None
        self._cur_band_mag = self._band_mag()
        if cfg.subpixel == "dft":
            # Cross-power weights |S_cur||S_ref| turn the phase-only band back
            # into a matched filter: noise-only frequencies get little weight.
            band = self.fft.cross[:, self._band_rows[:, None], self._band_cols[None, :]]
            band *= self._cur_band_mag * ref.band_mag
        self.fft.inverse()
        corr = self.fft.real  # (n, ey, ex), scaled by ey·ex
        scale = 1.0 / (ey * ex)

        # Top-K peaks in the search region, with non-maximum suppression.
        region = corr[:, self._reg_rows[:, None], self._reg_cols[None, :]]
        hy, wx = region.shape[1:]
        flat = region.reshape(n, -1)
        k = cfg.peaks
        cand_y = np.empty((n, k), dtype=np.intp)
        cand_x = np.empty((n, k), dtype=np.intp)
        cand_v = np.empty((n, k), dtype=np.float32)
        rows = self._rows
        offs = np.arange(-NMS_RADIUS, NMS_RADIUS + 1)
        for j in range(k):
            idx = np.argmax(flat, axis=1)
            cand_v[:, j] = flat[rows, idx]
            iy, ix = np.divmod(idx, wx)
            cand_y[:, j] = iy - my
            cand_x[:, j] = ix - mx
            if j + 1 < k:
                yy = np.clip(iy[:, None] + offs, 0, hy - 1)
                xx = np.clip(ix[:, None] + offs, 0, wx - 1)
                region[rows[:, None, None], yy[:, :, None], xx[:, None, :]] = -np.inf

        # Verify each candidate by the MSE between the two gradient blocks.
        mse = self._candidate_mse(ref, grad, top, left, cand_y, cand_x)
        mse[~np.isfinite(cand_v) | (cand_v <= 0)] = np.inf
        best = np.argmin(mse, axis=1)
        sy = cand_y[rows, best]
        sx = cand_x[rows, best]
        best_mse = mse[rows, best]
        peak = cand_v[rows, best].astype(np.float64) * scale

        # Sub-pixel refinement around the chosen peak.
        if band is not None:
            fx, fy, ok = self._dft_peak(band, sx, sy)
            ok_x = ok_y = ok
        else:
            ny = (sy[:, None] + np.array([-1, 0, 1])) % ey
            nx = (sx[:, None] + np.array([-1, 0, 1])) % ex
            nb = corr[rows[:, None, None], ny[:, :, None], nx[:, None, :]].astype(np.float64)
            fy, ok_y = _subpixel(nb[:, :, 1] * scale, cfg.subpixel)
            fx, ok_x = _subpixel(nb[:, 1, :] * scale, cfg.subpixel)

        vec = np.empty((n, 2), dtype=np.float64)
        vec[:, 0] = (left - ref.left) + sx + fx
        vec[:, 1] = (top - ref.top) + sy + fy
        measured = (
            inside & np.isfinite(best_mse) & ok_x & ok_y & (np.abs(sy) < my) & (np.abs(sx) < mx)
        )
        cx, cy = self._centre_offset
        centres = np.column_stack([ref.left + cx, ref.top + cy]).astype(np.float64)
        result = BlockMeasurement(
            centres_px=centres,
            vectors_px=vec,
            confidence=peak,
            mse=np.where(np.isfinite(best_mse), best_mse, np.nan),
            measured=measured,
        )
        return result, top, left

    def _dft_peak(
        self, band: npt.NDArray[np.complex64], sx: IArr, sy: IArr
    ) -> tuple[F64, F64, BArr]:
        """Continuous maximum of the band-limited correlation surface.

        ``c(p) = Re Σ_k w_k R_k exp(2πi k·p)`` over the low-frequency band of
        the normalised cross-power spectrum ``R``, maximised by Newton steps
        from the integer peak with analytic gradient and Hessian. For a pure
        translation ``R_k = A_k exp(-2πi k·d)`` with ``A_k ≥ 0`` and
        symmetric, so the maximum lies exactly at ``d`` whatever the texture's
        spectrum (no peak-shape model, hence no pixel-locking bias).

        Returns the offsets ``(fx, fy)`` from the integer peak and a validity mask.
        """
        r = band.astype(np.complex128) * self._band_w
        fy = self._fy
        fx = self._fx
        px = sx.astype(np.float64)
        py = sy.astype(np.float64)
        two_pi = 2.0 * np.pi
        ok = np.ones(px.shape, dtype=bool)
        step = np.zeros(px.shape)
        for _ in range(_NEWTON_STEPS):
            ey_ = np.exp(1j * two_pi * fy[None, :] * py[:, None])  # (n, Ly)
            ex_ = np.exp(1j * two_pi * fx[None, :] * px[:, None])  # (n, Lx)
            z = r * ey_[:, :, None] * ex_[:, None, :]
            zr, zi = z.real, z.imag
            gx = -two_pi * np.einsum("nyx,x->n", zi, fx)
            gy = -two_pi * np.einsum("nyx,y->n", zi, fy)
            hxx = -(two_pi**2) * np.einsum("nyx,x->n", zr, fx * fx)
            hyy = -(two_pi**2) * np.einsum("nyx,y->n", zr, fy * fy)
            hxy = -(two_pi**2) * np.einsum("nyx,y,x->n", zr, fy, fx)
            det = hxx * hyy - hxy * hxy
            concave = (hxx < 0) & (det > 0)
            safe = np.where(concave, det, 1.0)
            # Newton step where the surface is concave, else a bounded
            # gradient-ascent step towards the peak.
            newton_x = -(hyy * gx - hxy * gy) / safe
            newton_y = -(hxx * gy - hxy * gx) / safe
            step_x = np.where(concave, newton_x, np.sign(gx) * _MAX_STEP_PX)
            step_y = np.where(concave, newton_y, np.sign(gy) * _MAX_STEP_PX)
            step_x = np.clip(step_x, -_MAX_STEP_PX, _MAX_STEP_PX)
            step_y = np.clip(step_y, -_MAX_STEP_PX, _MAX_STEP_PX)
            px += step_x
            py += step_y
            step = np.hypot(step_x, step_y)
        off_x = px - sx
        off_y = py - sy
        ok &= (step < _CONVERGED_PX) & (np.abs(off_x) <= 3.0) & (np.abs(off_y) <= 3.0)
        return np.where(ok, off_x, 0.0), np.where(ok, off_y, 0.0), ok

    def _candidate_mse(
        self,
        ref: ReferenceSpectra,
        grad: F32,
        top: IArr,
        left: IArr,
        cand_y: IArr,
        cand_x: IArr,
    ) -> F64:
        """Mean squared difference of the inner blocks at each candidate shift.

        Sampled on a lattice of ``mse_stride_px``; the mean difference is
        removed (an offset is not a mismatch). Pixels of the shifted block
        outside the current image are left out (the overlap); fewer than a
        quarter of the samples in the overlap gives ``inf``.
        """
        rows_img, cols_img = grad.shape
        iy0, ix0 = self._inner
        ry = (ref.top + iy0)[:, None] + self._mse_rows[None, :]  # (n, Ly)
        rx = (ref.left + ix0)[:, None] + self._mse_cols[None, :]  # (n, Lx)
        ty = (top - ref.top)[:, None] + cand_y  # (n, K)
        tx = (left - ref.left)[:, None] + cand_x
        cy = ry[:, None, :] + ty[:, :, None]  # (n, K, Ly)
        cx = rx[:, None, :] + tx[:, :, None]  # (n, K, Lx)
        vy = (cy >= 0) & (cy < rows_img)
        vx = (cx >= 0) & (cx < cols_img)
        np.clip(cy, 0, rows_img - 1, out=cy)
        np.clip(cx, 0, cols_img - 1, out=cx)
        cur = grad[cy[:, :, :, None], cx[:, :, None, :]]
        refb = ref.grad[ry[:, None, :, None], rx[:, None, None, :]]
        diff = (cur - refb).astype(np.float64)
        w = (vy[:, :, :, None] & vx[:, :, None, :]).astype(np.float64)
        cnt = w.sum(axis=(2, 3))
        total = self._mse_rows.size * self._mse_cols.size
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (diff * w).sum(axis=(2, 3)) / cnt
            mse: F64 = (((diff - mean[:, :, None, None]) ** 2) * w).sum(axis=(2, 3)) / cnt
        mse[cnt < 0.25 * total] = np.inf
        return mse


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

"""Compiled per-block passes of the block engine (Numba, no GIL).

NumPy runs each step of the per-frame work (cut out and window the blocks,
normalise the spectra, multiply by the reference, search the peaks, verify
them by MSE, refine to sub-pixel) as a separate pass over the whole block
stack, each holding the GIL for its many small operations. These kernels do
the same arithmetic block by block in one or two passes, release the GIL,
and so run concurrently on the engine's threads beside the FFTW
transforms. The per-block kernels work on one batch of blocks;
the small ones around them (gradient image with the frame checks' figures,
window placement, block assembly, medians, the MAD rule) on the whole frame. All
write into arrays the caller owns; they allocate only small scratch arrays (per-block rows,
candidates, sub-pixel sums).

Complex spectra are passed as float32 views with interleaved real and
imaginary parts (``spectrum.view(np.float32)``: shape ``(n, rows,
2 * (cols // 2 + 1))``), so that the loops are plain float32 arithmetic the
compiler vectorises (the normalisation and cross-power loop compiles to
packed square roots, divisions and products); the reference spectra are
interleaved int16 fixed point (see :func:`normalise_reference`).

Results do not depend on the thread count: every block is computed on its
own, in a fixed order, and the split into batches is fixed by the frame
layout.

:func:`measure_batches` runs a thread's whole share of a measuring pass,
FFTs included (FFTW's execute functions called through their addresses),
in one call: no GIL is taken between batches.

The kernels are compiled on first use and cached on disk by Numba
(``__pycache__`` beside this file, or ``$NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = [
    "STRIP_CHUNK",
    "assemble",
    "dft_subpixel",
    "forward_strips",
    "gradient_x",
    "masked_mean_std",
    "masked_medians",
    "measure_batches",
    "normalise_cross",
    "normalise_reference",
    "pick_peaks",
    "place_windows",
    "publish",
    "reject_mad",
    "reject_paper",
    "row_groups",
    "row_means",
    "select_blocks",
    "subpixel_3pt",
    "trend_select",
    "usable_blocks",
]

_jit = numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
#: For loops over finite values only (maxima): all fastmath flags, which drop
#: the NaN handling of the comparisons (the float maxima still stay scalar
#: loops, about one element per cycle, measured).
_jit_finite = numba.njit(
    nogil=True, cache=True, error_model="numpy", boundscheck=False, fastmath=True
)
#: For sums (the sub-pixel step, the gradient pass's counts): reassociation
#: (vectorised sums, last bits depending on the compiled order) but no
#: assumption of finite values.
_jit_sums = numba.njit(
    nogil=True,
    cache=True,
    error_model="numpy",
    boundscheck=False,
    fastmath={"reassoc", "contract", "nsz", "arcp"},
)

#: Newton iterations of the ``dft`` sub-pixel method after the quadratic start
#: (quadratic convergence: the second step checks that the first converged).
NEWTON_STEPS = 2
#: Largest Newton step (px) and the last step below which it has converged.
MAX_STEP_PX = 1.0
CONVERGED_PX = 0.02


@_jit_sums
def gradient_x(heights, out):  # type: ignore[no-untyped-def]
    """``out[r, c] = heights[r, c + 1] - heights[r, c]``, the difference taken
    in the heights' precision and then rounded to ``out``'s float32; returns
    what the frame checks need, found in the same pass: ``(finite, nonzero,
    uniform)``, whether every difference is finite, how many are non-zero
    (``-0.0`` counts as zero) and whether all are equal.

    Every pixel enters a difference, and a difference with a NaN or infinite
    pixel is NaN or infinite, so ``finite`` is False whenever the heights
    have such a pixel (and also when a difference of finite heights
    overflows float32). One pass, with the sums vectorised: a third of the
    time of the NumPy reductions it replaces (minimum and maximum of heights
    and gradient, count) on a 512² frame fresh from memory.
    """
    first = np.float32(heights[0, 1] - heights[0, 0])
    nonzero = np.int32(0)
    differ = np.int32(0)
    # Σ 0·g is 0 for finite g and NaN otherwise (not folded away: no
    # finite-math assumption among the flags of _jit_sums).
    zero = np.float32(0.0)
    for r in range(out.shape[0]):
        h = heights[r]
        o = out[r]
        for c in range(o.size):
            v = np.float32(h[c + 1] - h[c])
            o[c] = v
            nonzero += np.int32(v != 0)
            differ += np.int32(v != first)
            zero += v * np.float32(0.0)
    return zero == 0, nonzero, differ == 0


@_jit_sums
def weight_centroids(grad, top, left, window, out):  # type: ignore[no-untyped-def]
    """Centre of each block's correlation weight, relative to its window's
    centre: ``out[i] = (x, y)`` centroid of ``w² (g − ḡ)²`` over the window at
    ``(top[i], left[i])`` of ``grad`` (``ḡ`` its window-weighted mean),
    minus ``((Ex − 1)/2, (Ey − 1)/2)``; zeros for a block without texture.

    A block's sub-pixel shift is the average of its content's local shifts
    weighted about so; when the shift varies over the window (drift while
    its rows are scanned), it is the shift at this point, not at the
    window's centre.
    """
    n = top.size
    ey, ex = window.shape
    for i in range(n):
        t = top[i]
        le = left[i]
        sw = 0.0
        swg = 0.0
        for r in range(ey):
            for c in range(ex):
                w = np.float64(window[r, c])
                sw += w
                swg += w * grad[t + r, le + c]
        mean = swg / sw if sw > 0 else 0.0
        s0 = 0.0
        sx = 0.0
        sy = 0.0
        for r in range(ey):
            row = 0.0
            for c in range(ex):
                w = np.float64(window[r, c])
                d = grad[t + r, le + c] - mean
                e = w * w * d * d
                row += e
                sx += e * c
            s0 += row
            sy += row * r
        if s0 > 0 and math.isfinite(s0):
            out[i, 0] = sx / s0 - 0.5 * (ex - 1)
            out[i, 1] = sy / s0 - 0.5 * (ey - 1)
        else:
            out[i, 0] = 0.0
            out[i, 1] = 0.0


@_jit
def _remove_mean(spec, i, w_rows, w_cols, w_vals, w_sum):  # type: ignore[no-untyped-def]
    """Subtract block ``i``'s window-weighted mean: the window's DFT (a few
    non-zero terms ``w_vals`` at ``(w_rows, w_cols)``) times the mean.

    The zero frequency is then exactly zero by construction; it is set so,
    because the rounding left by the subtraction (large on height images
    with a big mean) would otherwise be normalised to unit magnitude and
    enter the correlation as one term of pure noise."""
    mean = spec[i, 0, 0] / w_sum
    for j in range(w_rows.size):
        r = w_rows[j]
        c = 2 * w_cols[j]
        spec[i, r, c] -= mean * w_vals[j, 0]
        spec[i, r, c + 1] -= mean * w_vals[j, 1]
    spec[i, 0, 0] = 0.0
    spec[i, 0, 1] = 0.0


@_jit
def _floor(spec, i, eps_rel, floor, abs2):  # type: ignore[no-untyped-def]
    """Magnitude floor of block ``i``: ``max(eps_rel · max|S|, floor)``;
    fills ``abs2`` (rows, half) with ``|S|² = re² + im²`` on the way.

    The largest ``|S|²`` is taken as the largest int32 bit pattern of the
    stored squares (the same order for non-negative floats): an integer
    maximum, which the compiler vectorises, unlike a float one."""
    for r in range(abs2.shape[0]):
        row = spec[i, r]
        out = abs2[r]
        for k in range(out.size):
            out[k] = row[2 * k] * row[2 * k] + row[2 * k + 1] * row[2 * k + 1]
    bits = abs2.view(np.int32)
    peak = np.zeros(1, dtype=np.int32)
    for r in range(bits.shape[0]):
        row_bits = bits[r]
        for k in range(row_bits.size):
            v = row_bits[k]
            peak[0] = v if v > peak[0] else peak[0]
    peak2 = peak.view(np.float32)[0]
    return np.float32(max(eps_rel * math.sqrt(peak2), floor))


@_jit
def _band_row(r, rows, ky):  # type: ignore[no-untyped-def]
    """Band row (``ky = -ky_max .. +ky_max``) of spectrum row ``r``, or -1."""
    if r <= ky:
        return r + ky
    if r >= rows - ky:
        return r - (rows - ky)
    return -1


@_jit
def _magnitudes(abs2, out):  # type: ignore[no-untyped-def]
    """``out[k] = sqrt(abs2[k])`` for the first ``out.size`` elements (the
    magnitudes of a spectrum row from its ``|S|²``)."""
    for k in range(out.size):
        out[k] = math.sqrt(abs2[k])


@_jit
def _normalised(re, im, abs2, a):  # type: ignore[no-untyped-def]
    """``(re, im) / (|re + i im| + a)``, given ``abs2 = re² + im²``."""
    inv = np.float32(1.0) / (np.float32(math.sqrt(abs2)) + a)
    return re * inv, im * inv


#: Fixed-point scale of the stored reference spectra: components of
#: ``conj(Ŝ) · ramp`` (magnitude below 1) as int16 multiples of 1 / 32767.
REF_SCALE = 32767.0


@_jit
def _to_fixed(x):  # type: ignore[no-untyped-def]
    """``x`` (|x| ≤ 1) to int16 multiples of ``1 / REF_SCALE``, rounded."""
    return np.int16(x * np.float32(REF_SCALE) + (np.float32(0.5) if x >= 0 else np.float32(-0.5)))


@_jit
def _reference_row(s, abs2, ramp, o, a):  # type: ignore[no-untyped-def]
    """``o = conj(s / (|s| + a)) · ramp`` over an interleaved complex row
    (``abs2``: its ``|s|²``), in fixed point (int16, see :data:`REF_SCALE`)."""
    for k in range(s.size // 2):
        re, im = _normalised(s[2 * k], s[2 * k + 1], abs2[k], a)
        o[2 * k] = _to_fixed(re * ramp[2 * k] + im * ramp[2 * k + 1])
        o[2 * k + 1] = _to_fixed(re * ramp[2 * k + 1] - im * ramp[2 * k])


@_jit
def normalise_reference(  # type: ignore[no-untyped-def]
    blocks, spec, w_rows, w_cols, w_vals, w_sum, eps_rel, floor, ky, kx, ramp, out, band_mag
):
    """Reference spectra: remove each block's weighted mean from ``spec`` (in
    place), write ``out = conj(S / (|S| + a)) · ramp`` and ``band_mag = |S|``
    in the sub-pixel band (rows ``-ky..ky``, columns ``0..kx``).

    The phase ramp ``exp(-2πi k·m)`` (``ramp``: one block's spectrum shape)
    shifts every correlation by ``m``, the search radius, so that shifts
    ``-m..m`` come out of the inverse FFT as rows and columns ``0..2m``.

    ``spec[k]`` belongs to block ``blocks[k]``, the index of ``out`` and
    ``band_mag``. spec, ramp : (len(blocks), rows, 2·half) and (rows,
    2·half) float32 (interleaved complex); out : (n, rows, 2·half) int16
    (interleaved); w_vals : (m, 2) float32; band_mag : (n, 2·ky + 1, kx +
    1) float32.
    """
    rows = spec.shape[1]
    abs2 = np.empty((rows, spec.shape[2] // 2), dtype=np.float32)
    for k in range(blocks.size):
        i = blocks[k]
        _remove_mean(spec, k, w_rows, w_cols, w_vals, w_sum)
        a = _floor(spec, k, eps_rel, floor, abs2)
        for r in range(rows):
            b = _band_row(r, rows, ky)
            if b >= 0:
                _magnitudes(abs2[r], band_mag[i, b])
            _reference_row(spec[k, r], abs2[r], ramp[r], out[i, r], a)


@_jit
def _cross_row(s, abs2, q, a):  # type: ignore[no-untyped-def]
    """``s = s / (|s| + a) · q`` in place over an interleaved complex row
    (``abs2``: its ``|s|²``; ``q`` in fixed point, see :data:`REF_SCALE`).
    The fixed-point scale goes into the one division per element, so ``q``
    is used as it is stored (two products fewer per element)."""
    unit = np.float32(1.0 / REF_SCALE)
    for k in range(s.size // 2):
        inv = unit / (np.float32(math.sqrt(abs2[k])) + a)
        re = s[2 * k] * inv
        im = s[2 * k + 1] * inv
        qr = np.float32(q[2 * k])
        qi = np.float32(q[2 * k + 1])
        s[2 * k] = re * qr - im * qi
        s[2 * k + 1] = re * qi + im * qr


@_jit
def normalise_cross(  # type: ignore[no-untyped-def]
    blocks,
    spec,
    w_rows,
    w_cols,
    w_vals,
    w_sum,
    eps_rel,
    floor,
    ky,
    kx,
    ref,
    ref_band_mag,
    ramp,
    keep,
    band_mag,
    band,
):
    """Current spectra against a reference, in one pass per block.

    Removes each block's window-weighted mean from ``spec`` and turns it in
    place into the normalised cross-power spectrum ``Ŝ · ref`` with
    ``Ŝ = S / (|S| + a)`` and ``ref`` the reference's ``conj(R̂) · ramp``
    (see :func:`normalise_reference`; int16): the input of the inverse FFT.
    Also writes ``band_mag = |S|`` in the sub-pixel band; if ``keep`` has
    blocks, ``keep = conj(Ŝ) · ramp`` in the reference's int16 form (the
    frame is to become the next reference);
    and, if ``band`` has blocks, the weighted band ``band = Ŝ · ref · |S| ·
    |R|`` of the ``dft`` sub-pixel method. ``spec``, ``ref``, ``ramp``,
    ``keep`` and ``band`` are interleaved complex (``ref`` and ``keep``
    int16, the others float32). ``spec[k]`` and ``band[k]`` belong to block
    ``blocks[k]``, the index of ``ref``, ``ref_band_mag``, ``keep`` and
    ``band_mag``.
    """
    n, rows = blocks.size, spec.shape[1]
    keeping = keep.shape[0] > 0
    with_band = band.shape[0] > 0
    abs2 = np.empty((rows, spec.shape[2] // 2), dtype=np.float32)
    for k in range(n):
        i = blocks[k]
        _remove_mean(spec, k, w_rows, w_cols, w_vals, w_sum)
        a = _floor(spec, k, eps_rel, floor, abs2)
        for r in range(rows):
            s = spec[k, r]
            b = _band_row(r, rows, ky)
            if b >= 0:
                _magnitudes(abs2[r], band_mag[i, b])
            if keeping:
                _reference_row(s, abs2[r], ramp[r], keep[i, r], a)
            _cross_row(s, abs2[r], ref[i, r], a)
            if b >= 0 and with_band:
                for c in range(kx + 1):
                    w = band_mag[i, b, c] * ref_band_mag[i, b, c]
                    band[k, b, 2 * c] = s[2 * c] * w
                    band[k, b, 2 * c + 1] = s[2 * c + 1] * w


@_jit_finite
def _row_max(row, x0, x1):  # type: ignore[no-untyped-def]
    """Highest value of ``row[x0..x1]`` (finite values)."""
    m = row[x0]
    for c in range(x0, x1 + 1):
        m = max(m, row[c])
    return m


@_jit
def _suppressed(iy, ix, acc_y, acc_x, n_acc, nms):  # type: ignore[no-untyped-def]
    """Whether ``(iy, ix)`` lies in the square of half-size ``nms`` around
    one of the ``n_acc`` accepted peaks."""
    for q in range(n_acc):  # noqa: SIM110 (a generator in any() does not compile)
        if abs(iy - acc_y[q]) <= nms and abs(ix - acc_x[q]) <= nms:
            return True
    return False


@_jit
def _row_max_masked(row, iy, x0, x1, acc_y, acc_x, n_acc, nms):  # type: ignore[no-untyped-def]
    """Highest value of ``row[x0..x1]`` outside the suppressed squares
    (``-inf`` if none is left): the plain maximum over each gap between the
    column intervals of the squares that cover row ``iy``."""
    starts = np.empty(n_acc, dtype=np.intp)
    m = 0
    for q in range(n_acc):  # the covering squares' left columns, sorted
        if abs(iy - acc_y[q]) <= nms:
            a = acc_x[q] - nms
            k = m
            while k > 0 and starts[k - 1] > a:
                starts[k] = starts[k - 1]
                k -= 1
            starts[k] = a
            m += 1
    best = -np.inf
    col = x0
    for k in range(m):  # each interval is [start, start + 2·nms]
        if starts[k] > col:
            best = max(best, _row_max(row, col, min(starts[k], x1 + 1) - 1))
        col = max(col, starts[k] + 2 * nms + 1)
        if col > x1:
            return best
    if col <= x1:
        best = max(best, _row_max(row, col, x1))
    return best


@_jit
def _first_column(row, iy, x0, x1, value, acc_y, acc_x, n_acc, nms):  # type: ignore[no-untyped-def]
    """First column of ``row[x0..x1]`` holding ``value`` outside the
    suppressed squares."""
    for ix in range(x0, x1 + 1):
        if row[ix] == value and not _suppressed(iy, ix, acc_y, acc_x, n_acc, nms):
            return ix
    return x0


@_jit
def _block_mse(  # type: ignore[no-untyped-def]
    grad, ref_grad, y0, x0, shift_y, shift_x, mse_rows, mse_cols
):
    """Mean squared difference (mean removed) between the reference's inner
    block at ``(y0, x0)`` and the current frame shifted by ``(shift_y,
    shift_x)``, on the lattice ``mse_rows × mse_cols``. Samples falling
    outside the current image are left out; fewer than a quarter inside
    gives ``inf``."""
    rows_img, cols_img = grad.shape
    total = mse_rows.size * mse_cols.size
    s1 = 0.0
    s2 = 0.0
    cnt = 0
    for a in range(mse_rows.size):
        ry = y0 + mse_rows[a]
        cy = ry + shift_y
        if cy < 0 or cy >= rows_img:
            continue
        for b in range(mse_cols.size):
            rx = x0 + mse_cols[b]
            cx = rx + shift_x
            if cx < 0 or cx >= cols_img:
                continue
            d = np.float64(grad[cy, cx] - ref_grad[ry, rx])
            s1 += d
            s2 += d * d
            cnt += 1
    if cnt < 0.25 * total:
        return np.inf
    mean = s1 / cnt
    return max(s2 / cnt - mean * mean, 0.0)


@_jit
def pick_peaks(  # type: ignore[no-untyped-def]
    blocks,
    corr,
    search,
    peaks,
    ratio,
    nms,
    grad,
    ref_grad,
    ref_top,
    ref_left,
    top,
    left,
    inner,
    mse_rows,
    mse_cols,
    out_sy,
    out_sx,
    out_peak,
    out_mse,
):
    """Top-K correlation peaks per block, verified by MSE.

    ``corr[i, iy, ix]`` is block ``i``'s correlation at the shift ``(iy - my,
    ix - mx)`` (rows and columns ``0..2m``; ``search = (ry, rx, my, mx)``).
    Searches shifts within ``±(ry, rx)`` (``ry ≤ my``, ``rx ≤ mx``) for up
    to ``peaks`` maxima, greedily, each at least ``nms`` px (per axis)
    from the previous ones; a peak is a candidate while it is positive and
    at least ``ratio`` of the block's highest. Each candidate is verified by
    :func:`_block_mse` of the inner blocks (``inner = (iy0, ix0)`` offset in
    the window) at the total shift ``window move + peak``; the lowest MSE
    wins (the first on ties; with no candidate, the highest peak and
    ``inf``). Ties between equal correlation values go to the first in
    row-major order of the region.

    ``corr[k]`` belongs to block ``blocks[k]``, the index of the per-block
    arrays (window corners and outputs). Writes, per block: the integer
    shift ``out_sy``, ``out_sx``, the
    unnormalised correlation value ``out_peak`` and ``out_mse``. The search
    rows' maxima are found once; after each accepted peak only
    the rows its suppressed square covers are scanned again, and the column
    of a peak is looked up only in the row that wins.
    """
    n = blocks.size
    ry, rx, my, mx = search[0], search[1], search[2], search[3]
    y0r, y1r = my - ry, my + ry
    x0r, x1r = mx - rx, mx + rx
    height = y1r - y0r + 1
    row_best = np.empty(height, dtype=np.float32)
    acc_y = np.empty(peaks, dtype=np.intp)
    acc_x = np.empty(peaks, dtype=np.intp)
    for k in range(n):
        i = blocks[k]
        for h in range(height):
            row_best[h] = _row_max(corr[k, y0r + h], x0r, x1r)
        first = -np.inf
        best_mse = np.inf
        best_y = 0
        best_x = 0
        best_v = -np.inf
        for j in range(peaks):
            v = -np.inf
            hy = -1
            for h in range(height):
                if row_best[h] > v:
                    v = row_best[h]
                    hy = h
            if hy < 0:
                break
            py = y0r + hy
            px = _first_column(corr[k, py], py, x0r, x1r, v, acc_y, acc_x, j, nms)
            if j == 0:
                first = v
                best_y, best_x, best_v = py, px, v
            if not (v > 0 and v >= ratio * first):
                break  # later peaks are lower: no candidates either
            mse = _block_mse(
                grad,
                ref_grad,
                ref_top[i] + inner[0],
                ref_left[i] + inner[1],
                (top[i] - ref_top[i]) + (py - my),
                (left[i] - ref_left[i]) + (px - mx),
                mse_rows,
                mse_cols,
            )
            if mse < best_mse:
                best_mse = mse
                best_y, best_x, best_v = py, px, v
            acc_y[j] = py
            acc_x[j] = px
            if j + 1 < peaks:
                for h in range(max(0, hy - nms), min(height, hy + nms + 1)):
                    row_best[h] = _row_max_masked(
                        corr[k, y0r + h],
                        y0r + h,
                        x0r,
                        x1r,
                        acc_y,
                        acc_x,
                        j + 1,
                        nms,
                    )
        out_sy[i] = best_y - my
        out_sx[i] = best_x - mx
        out_peak[i] = best_v
        out_mse[i] = best_mse


@_jit
def _ascent_step(gx, gy, hxx, hyy, hxy):  # type: ignore[no-untyped-def]
    """Newton step towards a maximum where the Hessian is negative definite,
    else a unit gradient-ascent step; both bounded by ``MAX_STEP_PX``."""
    det = hxx * hyy - hxy * hxy
    if hxx < 0 and det > 0:
        sx = -(hyy * gx - hxy * gy) / det
        sy = -(hxx * gy - hxy * gx) / det
    else:
        sx = np.sign(gx)
        sy = np.sign(gy)
    return (
        min(max(sx, -MAX_STEP_PX), MAX_STEP_PX),
        min(max(sy, -MAX_STEP_PX), MAX_STEP_PX),
    )


@_jit_sums
def _phases(f, d, out_re, out_im):  # type: ignore[no-untyped-def]
    """``out = exp(2πi f[j] d)`` (real and imaginary parts) for evenly spaced
    frequencies ``f`` (a geometric sequence: two complex exponentials, then
    products)."""
    z = np.exp(2j * math.pi * f[0] * d)
    step = np.exp(2j * math.pi * (f[1] - f[0]) * d)
    for j in range(f.size):
        out_re[j] = z.real
        out_im[j] = z.imag
        z *= step


@_jit_sums
def dft_subpixel(  # type: ignore[no-untyped-def]
    blocks, band, fy, fx, sy, sx, shift, envelope, out_fx, out_fy, out_ok
):
    """Continuous maximum of the band-limited correlation, per block.

    ``c(p) = Re Σ_k w_k R_k exp(2πi k·p)`` over the band ``R`` (interleaved
    complex; rows at the evenly spaced frequencies ``fy``, columns at
    ``fx = 0, 1/E, ...`` with Hermitian weight 2 for ``fx > 0``), centred on
    the integer peak ``(sy, sx)``. A quadratic through ``c`` at the best of
    the 5×5 integer offsets around the peak starts :data:`NEWTON_STEPS`
    Newton steps with the analytic gradient and Hessian of ``log c``, which
    also divide out the window autocorrelation
    ``A(p) ≈ exp(-κx px²/2 - κy py²/2)`` (``envelope = (κy, κx)``).

    For a pure translation ``R_k = A_k exp(-2πi k·d)`` with ``A_k ≥ 0``
    symmetric in ``k``, so the maximum lies exactly at ``d`` whatever the
    texture's spectrum: no peak-shape model, no pixel-locking bias.

    ``shift = (my, mx)`` is the shift the reference's phase ramp put into
    the band (see :func:`normalise_reference`; zeros for none).

    Writes the offsets from the integer peak and whether the iteration
    converged within 3 px of it (offsets 0 where it did not).

    ``band[k]`` belongs to block ``blocks[k]``, the index of the per-block
    arrays ``sy``, ``sx`` and the outputs.
    """
    n, ly = blocks.size, band.shape[1]
    lx = fx.size
    two_pi = 2.0 * math.pi
    k_y, k_x = envelope[0], envelope[1]
    # Complex values as separate real and imaginary float64 arrays: the
    # sums over the band then compile to packed arithmetic.
    r0_re = np.empty((ly, lx))
    r0_im = np.empty((ly, lx))
    t5_re = np.empty((5, ly))
    t5_im = np.empty((5, ly))
    c5 = np.empty((5, 5))
    px_re = np.empty(lx)
    px_im = np.empty(lx)
    py_re = np.empty(ly)
    py_im = np.empty(ly)
    fx2 = fx * fx
    # exp(2πi f·o) at the integer offsets o = -2..2 (the same for every block).
    ex5_re = np.empty((5, lx))
    ex5_im = np.empty((5, lx))
    ey5_re = np.empty((5, ly))
    ey5_im = np.empty((5, ly))
    for o in range(5):
        _phases(fx, o - 2.0, ex5_re[o], ex5_im[o])
        _phases(fy, o - 2.0, ey5_re[o], ey5_im[o])
    for k in range(n):
        i = blocks[k]
        # r0 = w · R · exp(2πi k·s): the band centred on the integer peak.
        _phases(fx, float(sx[i] + shift[1]), px_re, px_im)
        _phases(fy, float(sy[i] + shift[0]), py_re, py_im)
        for x in range(1, lx):
            px_re[x] *= 2.0
            px_im[x] *= 2.0
        for y in range(ly):
            a_re, a_im = py_re[y], py_im[y]
            for x in range(lx):
                b_re = np.float64(band[k, y, 2 * x])
                b_im = np.float64(band[k, y, 2 * x + 1])
                u_re = b_re * a_re - b_im * a_im
                u_im = b_re * a_im + b_im * a_re
                r0_re[y, x] = u_re * px_re[x] - u_im * px_im[x]
                r0_im[y, x] = u_re * px_im[x] + u_im * px_re[x]
        # c at the 5×5 integer offsets -2..2 (separable sums).
        for y in range(ly):
            for b in range(5):
                s_re = 0.0
                s_im = 0.0
                for x in range(lx):
                    s_re += r0_re[y, x] * ex5_re[b, x] - r0_im[y, x] * ex5_im[b, x]
                    s_im += r0_re[y, x] * ex5_im[b, x] + r0_im[y, x] * ex5_re[b, x]
                t5_re[b, y] = s_re
                t5_im[b, y] = s_im
        for a in range(5):
            for b in range(5):
                acc = 0.0
                for y in range(ly):
                    acc += t5_re[b, y] * ey5_re[a, y] - t5_im[b, y] * ey5_im[a, y]
                c5[a, b] = acc
        ba = 0
        bb = 0
        for a in range(5):
            for b in range(5):
                if c5[a, b] > c5[ba, bb]:
                    ba, bb = a, b
        ba = min(max(ba, 1), 3)
        bb = min(max(bb, 1), 3)
        gx = 0.5 * (c5[ba, bb + 1] - c5[ba, bb - 1])
        gy = 0.5 * (c5[ba + 1, bb] - c5[ba - 1, bb])
        hxx = c5[ba, bb + 1] - 2.0 * c5[ba, bb] + c5[ba, bb - 1]
        hyy = c5[ba + 1, bb] - 2.0 * c5[ba, bb] + c5[ba - 1, bb]
        hxy = 0.25 * (
            c5[ba + 1, bb + 1] - c5[ba + 1, bb - 1] - c5[ba - 1, bb + 1] + c5[ba - 1, bb - 1]
        )
        qx, qy = _ascent_step(gx, gy, hxx, hyy, hxy)
        dx = qx + (bb - 2)
        dy = qy + (ba - 2)
        step = np.inf
        for _ in range(NEWTON_STEPS):
            _phases(fx, dx, px_re, px_im)
            _phases(fy, dy, py_re, py_im)
            # Σ z, Σ z fx, Σ z fx², Σ z fy, Σ z fx fy, Σ z fy² (the parts used)
            m00_re = 0.0
            m10_im = 0.0
            m20_re = 0.0
            m01_im = 0.0
            m11_re = 0.0
            m02_re = 0.0
            for y in range(ly):
                t0_re = 0.0
                t0_im = 0.0
                t1_re = 0.0
                t1_im = 0.0
                t2_re = 0.0
                t2_im = 0.0
                for x in range(lx):
                    z_re = r0_re[y, x] * px_re[x] - r0_im[y, x] * px_im[x]
                    z_im = r0_re[y, x] * px_im[x] + r0_im[y, x] * px_re[x]
                    t0_re += z_re
                    t0_im += z_im
                    t1_re += z_re * fx[x]
                    t1_im += z_im * fx[x]
                    t2_re += z_re * fx2[x]
                    t2_im += z_im * fx2[x]
                e_re, e_im = py_re[y], py_im[y]
                u0_re = t0_re * e_re - t0_im * e_im
                u0_im = t0_re * e_im + t0_im * e_re
                m00_re += u0_re
                m10_im += t1_re * e_im + t1_im * e_re
                m20_re += t2_re * e_re - t2_im * e_im
                m01_im += u0_im * fy[y]
                m11_re += (t1_re * e_re - t1_im * e_im) * fy[y]
                m02_re += u0_re * (fy[y] * fy[y])
            c0 = m00_re
            if c0 > 0:
                inv = 1.0 / c0
                gx = -two_pi * m10_im * inv
                gy = -two_pi * m01_im * inv
                hxx = -(two_pi**2) * m20_re * inv - gx * gx + k_x
                hyy = -(two_pi**2) * m02_re * inv - gy * gy + k_y
                hxy = -(two_pi**2) * m11_re * inv - gx * gy
                st_x, st_y = _ascent_step(
                    gx + k_x * (sx[i] + dx), gy + k_y * (sy[i] + dy), hxx, hyy, hxy
                )
                dx += st_x
                dy += st_y
                step = math.hypot(st_x, st_y)
            else:
                step = np.inf
        ok = step < CONVERGED_PX and abs(dx) <= 3.0 and abs(dy) <= 3.0
        out_ok[i] = ok
        out_fx[i] = dx if ok else 0.0
        out_fy[i] = dy if ok else 0.0


@_jit
def _gather(vectors, mask, axis, out):  # type: ignore[no-untyped-def]
    """Copy column ``axis`` of the rows of ``vectors`` where ``mask`` to the
    start of ``out``; returns their number."""
    m = 0
    for i in range(vectors.shape[0]):
        if mask[i]:
            out[m] = vectors[i, axis]
            m += 1
    return m


@_jit
def reject_mad(vectors, keep, threshold, floor, max_iter, out):  # type: ignore[no-untyped-def]
    """Iterated per-axis median/MAD outlier rule (see
    :mod:`afmdrift.registration._outliers`): ``out`` starts as ``keep``;
    while at least 3 blocks remain, blocks of ``keep`` whose robust z-score
    ``|v - median| / (1.4826 · max(MAD, floor))`` exceeds ``threshold`` on
    either axis are dropped, until nothing changes (at most ``max_iter``
    rounds).

    vectors : (n, 2) float64; keep, out : (n,) bool.
    """
    n = vectors.shape[0]
    out[:] = keep
    sel = np.empty(n)
    med = np.empty(2)
    scale = np.empty(2)
    for _ in range(max_iter):
        m = 0
        for i in range(n):
            m += 1 if out[i] else 0
        if m < 3:
            return m
        for axis in range(2):
            _gather(vectors, out, axis, sel)
            med[axis] = np.median(sel[:m])
            for i in range(m):
                sel[i] = abs(sel[i] - med[axis])
            scale[axis] = 1.4826 * max(np.median(sel[:m]), floor)
        changed = False
        for i in range(n):
            new = keep[i]
            for axis in range(2):
                if not (abs(vectors[i, axis] - med[axis]) / scale[axis] <= threshold):
                    new = False
            if new != out[i]:
                changed = True
            out[i] = new
        if not changed:
            break
    m = 0
    for i in range(n):
        m += 1 if out[i] else 0
    return m


@_jit
def _poly_fit(x, values, weights, mask, degree, coef):  # type: ignore[no-untyped-def]
    """Weighted least-squares polynomial ``Σ_k coef[k, axis]·x^k`` (degree
    ``degree``) through ``values`` (n, 2) at the rows where ``mask``, by its
    normal equations (Gaussian elimination with partial pivoting; at most
    3×3, rows scaled to [-1, 1]). A singular system (fewer distinct rows than
    coefficients) is fitted with the highest degree it determines (the
    higher coefficients zero); ``coef`` rows beyond ``degree`` are left as
    they are."""
    for d in range(degree + 1, 0, -1):
        a = np.zeros((d, d))
        b = np.zeros((d, 2))
        for i in range(x.shape[0]):
            if not mask[i]:
                continue
            w = weights[i]
            p_k = 1.0
            for k in range(d):
                p_j = 1.0
                for j in range(d):
                    a[k, j] += w * p_k * p_j
                    p_j *= x[i]
                b[k, 0] += w * p_k * values[i, 0]
                b[k, 1] += w * p_k * values[i, 1]
                p_k *= x[i]
        singular = False
        scale = max(abs(a[0, 0]), 1e-300)
        for col in range(d):
            piv = col
            for k in range(col + 1, d):
                if abs(a[k, col]) > abs(a[piv, col]):
                    piv = k
            if not abs(a[piv, col]) > 1e-12 * scale:
                singular = True
                break
            if piv != col:
                for j in range(d):
                    a[col, j], a[piv, j] = a[piv, j], a[col, j]
                for j in range(2):
                    b[col, j], b[piv, j] = b[piv, j], b[col, j]
            for k in range(col + 1, d):
                f = a[k, col] / a[col, col]
                for j in range(col, d):
                    a[k, j] -= f * a[col, j]
                for j in range(2):
                    b[k, j] -= f * b[col, j]
        if singular:
            continue
        for k in range(d, degree + 1):
            coef[k, 0] = 0.0
            coef[k, 1] = 0.0
        for col in range(d - 1, -1, -1):
            for j in range(2):
                s = b[col, j]
                for k in range(col + 1, d):
                    s -= a[col, k] * coef[k, j]
                coef[col, j] = s / a[col, col]
        return
    for k in range(degree + 1):
        coef[k, 0] = 0.0
        coef[k, 1] = 0.0


@_jit
def _poly_residual(x, vectors, coef, degree, residual):  # type: ignore[no-untyped-def]
    for i in range(x.shape[0]):
        for j in range(2):
            s = 0.0
            p_k = 1.0
            for k in range(degree + 1):
                s += coef[k, j] * p_k
                p_k *= x[i]
            residual[i, j] = vectors[i, j] - s


@_jit
def row_groups(rows, levels, group):  # type: ignore[no-untyped-def]
    """The distinct values of ``rows`` (block rows, px) into the start of
    ``levels``, sorted, and each row's index among them into ``group``;
    returns their number. rows, levels : (m,) float64; group : (m,) intp."""
    sorted_rows = np.sort(rows)
    n_lev = 0
    for k in range(rows.size):
        if n_lev == 0 or sorted_rows[k] != levels[n_lev - 1]:
            levels[n_lev] = sorted_rows[k]
            n_lev += 1
    for k in range(rows.size):
        group[k] = np.searchsorted(levels[:n_lev], rows[k])
    return n_lev


@_jit
def row_means(valid, vectors, row_px, weight_row_px, levels, counts, means, at):  # type: ignore[no-untyped-def]
    """The ``valid`` blocks grouped by their row (:func:`row_groups`), into
    the starts of the outputs: the distinct rows ``levels`` and, per row,
    the number of its blocks, their mean vector and the mean of their
    ``weight_row_px`` (each sum in block order). Returns ``(valid blocks,
    rows)``.

    valid : (n,) bool; vectors : (n, 2) float64; row_px, weight_row_px : (n,)
    float64.
    """
    n = valid.size
    rows = np.empty(n)
    m = 0
    for i in range(n):
        if valid[i]:
            rows[m] = row_px[i]
            m += 1
    group = np.empty(m, dtype=np.intp)
    n_lev = row_groups(rows[:m], levels, group)
    counts[:n_lev] = 0.0
    means[:n_lev] = 0.0
    at[:n_lev] = 0.0
    k = 0
    for i in range(n):
        if valid[i]:
            g = group[k]
            k += 1
            counts[g] += 1.0
            means[g, 0] += vectors[i, 0]
            means[g, 1] += vectors[i, 1]
            at[g] += weight_row_px[i]
    for g in range(n_lev):
        means[g, 0] /= counts[g]
        means[g, 1] /= counts[g]
        at[g] /= counts[g]
    return m, n_lev


@_jit
def trend_select(  # type: ignore[no-untyped-def]
    vectors, row_px, usable, threshold, floor, max_iter, max_degree, f_min, explained_min, out
):
    """The trend rule of :func:`afmdrift.registration._trend.select_by_trend`
    (see there), in one compiled pass: per-row medians, a weighted polynomial
    of degree up to ``max_degree`` through them, the MAD rule on the
    residuals (:func:`reject_mad`), refitted on the kept blocks and judged
    once more; the spreads and the F test of the trend against one mean.

    vectors : (n, 2) float64; row_px : (n,) float64; usable, out : (n,) bool.
    Returns ``(n_valid, spread_x, spread_y, significant)``.
    """
    n = vectors.shape[0]
    out[:] = usable
    m = 0
    for i in range(n):
        m += 1 if usable[i] else 0
    nan = math.nan
    if m < 3:
        return m, nan, nan, False
    rows = row_px[usable]
    vec = vectors[usable]
    levels = np.empty(m)
    group = np.empty(m, dtype=np.intp)
    n_lev = row_groups(rows, levels, group)
    levels = levels[:n_lev]
    degree = min(max_degree, n_lev - 1, max(0, (m - 2) // 3))
    scale = max(levels[-1] - levels[0], 1.0)
    centre = 0.0
    for k in range(n_lev):
        centre += levels[k]
    centre /= n_lev
    # per block row: the median of its usable blocks, weighted by their number
    medians = np.empty((n_lev, 2))
    counts = np.zeros(n_lev)
    for k in range(m):
        counts[group[k]] += 1.0
    sel = np.empty(m)
    for g in range(n_lev):
        for axis in range(2):
            c = 0
            for k in range(m):
                if group[k] == g:
                    sel[c] = vec[k, axis]
                    c += 1
            medians[g, axis] = np.median(sel[:c])
    x_lev = (levels - centre) / scale
    every = np.ones(n_lev, dtype=np.bool_)
    coef = np.zeros((max_degree + 1, 2))
    _poly_fit(x_lev, medians, counts, every, degree, coef)
    x_rows = (row_px - centre) / scale
    residual = np.empty((n, 2))
    _poly_residual(x_rows, vectors, coef, degree, residual)
    ones = np.ones(n)
    for _ in range(2):
        good = reject_mad(residual, usable, threshold, floor, max_iter, out)
        if good < degree + 2:
            break
        _poly_fit(x_rows, vectors, ones, out, degree, coef)
        _poly_residual(x_rows, vectors, coef, degree, residual)
    dof = good - (degree + 1)
    if dof < 1 or degree == 0:
        return good, nan, nan, False
    rss = np.zeros(2)
    mean = np.zeros(2)
    for i in range(n):
        if out[i]:
            for j in range(2):
                rss[j] += residual[i, j] * residual[i, j]
                mean[j] += vectors[i, j]
    mean /= good
    rss0 = np.zeros(2)
    for i in range(n):
        if out[i]:
            for j in range(2):
                rss0[j] += (vectors[i, j] - mean[j]) ** 2
    rss_sum = rss[0] + rss[1]
    rss0_sum = rss0[0] + rss0[1]
    gain = (rss0_sum - rss_sum) / (2 * degree)
    noise = max(rss_sum / (2 * dof), (floor / 2) ** 2)
    explained = 1.0 - rss_sum / max(rss0_sum, 1e-300)
    significant = gain / noise > f_min and explained >= explained_min
    return good, math.sqrt(rss[0] / dof), math.sqrt(rss[1] / dof), significant


@_jit
def reject_paper(vectors, keep, epsilon, out):  # type: ignore[no-untyped-def]
    """Yang et al.'s rule (see :mod:`afmdrift.registration._outliers`): ``out``
    = blocks of ``keep`` within ``epsilon`` (Euclidean) of the mean vector of
    ``keep``. Returns their number.

    vectors : (n, 2) float64; keep, out : (n,) bool.
    """
    n = vectors.shape[0]
    m = 0
    sx = 0.0
    sy = 0.0
    for i in range(n):
        if keep[i]:
            m += 1
            sx += vectors[i, 0]
            sy += vectors[i, 1]
    count = 0
    for i in range(n):
        out[i] = keep[i] and (math.hypot(vectors[i, 0] - sx / m, vectors[i, 1] - sy / m) <= epsilon)
        count += 1 if out[i] else 0
    return count


@_jit
def select_blocks(  # type: ignore[no-untyped-def]
    vectors, measured, placed, in_overlap, min_blocks, mad, threshold, floor, max_iter,
    epsilon, valid, stats,
):  # fmt: skip
    """The frame's valid blocks in one call: :func:`usable_blocks`, then the
    outlier rule (:func:`reject_mad` if ``mad``, else :func:`reject_paper`)
    into ``valid``, then :func:`masked_mean_std` (sample deviation) of the valid
    blocks into ``stats``. Returns ``(available, valid count)``."""
    usable = np.empty_like(measured)
    available = usable_blocks(measured, placed, in_overlap, min_blocks, usable)
    if mad:
        n_valid = reject_mad(vectors, usable, threshold, floor, max_iter, valid)
    else:
        n_valid = reject_paper(vectors, usable, epsilon, valid)
    masked_mean_std(vectors, valid, 1, stats)
    return available, n_valid


@_jit
def place_windows(  # type: ignore[no-untyped-def]
    ref_top, ref_left, dy, dx, max_top, max_left, near_y, near_x, top, left, placed, near
):
    """Window corners moved by the integer shift ``(dy, dx)`` and clamped
    into ``[0, max_top] × [0, max_left]``; ``placed`` where no clamping was
    needed, ``near`` where it was at most ``(near_y, near_x)``. Returns the
    number of placed windows."""
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


@_jit
def assemble(  # type: ignore[no-untyped-def]
    top, left, ref_top, ref_left, sy, sx, fy, fx, ok, mse, peak, area, near, my, mx, unbias,
    vectors, measured, confidence, median,
):  # fmt: skip
    """Block vectors ``(x, y)`` = window move + ``unbias`` (n, 2, 2) times
    (integer peak + sub-pixel offset), the shift under the window corrected
    for the block's window response (``BlockEngine.calibrate``), and
    whether each block was measured: window near its place, a
    verified (finite-MSE) peak inside the search (not on its edge), and a
    converged sub-pixel step. Also the peak ``confidence = peak / area``
    (the inverse FFT's scale), in place NaN for an infinite ``mse`` (no
    candidate verified), and the :func:`masked_medians` of the measured
    vectors. Returns the number of measured blocks."""
    for i in range(top.size):
        rx = sx[i] + fx[i]
        ry = sy[i] + fy[i]
        vectors[i, 0] = (left[i] - ref_left[i]) + unbias[i, 0, 0] * rx + unbias[i, 0, 1] * ry
        vectors[i, 1] = (top[i] - ref_top[i]) + unbias[i, 1, 0] * rx + unbias[i, 1, 1] * ry
        finite = np.isfinite(mse[i])
        measured[i] = near[i] and finite and ok[i] and abs(sy[i]) < my and abs(sx[i]) < mx
        if not finite:
            mse[i] = np.nan
        confidence[i] = np.float64(peak[i]) / area
    return masked_medians(vectors, measured, median)


@_jit
def masked_mean_std(vectors, mask, ddof, out):  # type: ignore[no-untyped-def]
    """Per-column mean (``out[0:2]``) and standard deviation (``out[2:4]``,
    divided by ``m − ddof`` as NumPy's ``std``; NaN unless more than ``ddof``
    rows) of the ``m`` rows of ``vectors`` (n, 2) where ``mask``; two passes,
    the sums in row order."""
    m = 0
    sx = 0.0
    sy = 0.0
    for i in range(vectors.shape[0]):
        if mask[i]:
            m += 1
            sx += vectors[i, 0]
            sy += vectors[i, 1]
    mx = sx / m if m > 0 else np.nan
    my = sy / m if m > 0 else np.nan
    qx = 0.0
    qy = 0.0
    for i in range(vectors.shape[0]):
        if mask[i]:
            qx += (vectors[i, 0] - mx) ** 2
            qy += (vectors[i, 1] - my) ** 2
    out[0] = mx
    out[1] = my
    out[2] = math.sqrt(qx / (m - ddof)) if m > ddof else np.nan
    out[3] = math.sqrt(qy / (m - ddof)) if m > ddof else np.nan


@_jit
def masked_medians(vectors, mask, out):  # type: ignore[no-untyped-def]
    """Per-column medians of the rows of ``vectors`` (n, 2) where ``mask``
    (NumPy's median: the mean of the two middle values for an even count);
    NaN when no row is selected. Returns the number of selected rows."""
    sel = np.empty(vectors.shape[0])
    m = 0
    for axis in range(2):
        m = _gather(vectors, mask, axis, sel)
        out[axis] = np.median(sel[:m]) if m > 0 else np.nan
    return m


@_jit
def usable_blocks(measured, placed, in_overlap, min_blocks, out):  # type: ignore[no-untyped-def]
    """``out = measured & placed``, or ``measured`` alone where that leaves
    fewer than ``min_blocks`` (frames so small that most windows had to be
    clamped). Returns the number of blocks available to be valid: those
    placed, or in the fallback those in the overlap."""
    n = measured.size
    count = 0
    available = 0
    for i in range(n):
        out[i] = measured[i] and placed[i]
        count += 1 if out[i] else 0
        available += 1 if placed[i] else 0
    if count >= min_blocks:
        return available
    available = 0
    for i in range(n):
        out[i] = measured[i]
        available += 1 if in_overlap[i] else 0
    return available


# -- the block pass as one call per thread ---------------------------------------

#: ``method`` codes of :func:`subpixel_3pt` (``config.subpixel``; ``dft`` is 0).
SUBPIXEL_CODES = {"dft": 0, "sinc": 1, "parabolic": 2, "gaussian": 3}


def _fftw_execute_typing(typingctx, fn, plan, src, dst):  # type: ignore[no-untyped-def]
    """Call the C function at address ``fn`` with the pointers ``(plan, src,
    dst)`` (all integers): one of FFTW's new-array execute functions. The
    address is a run-time value, so functions calling this stay cacheable."""
    if not all(isinstance(t, types.Integer) for t in (fn, plan, src, dst)):
        return None
    sig = types.void(fn, plan, src, dst)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [ptr, ptr, ptr])
        target = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(target, [builder.inttoptr(a, ptr) for a in args[1:]])
        return context.get_dummy_value()

    return sig, codegen


_fftw_execute: Any = intrinsic(_fftw_execute_typing)


def _is_int64_slot(counter: Any, index: Any) -> bool:
    """Whether ``(counter, index)`` types an element of an int64 array."""
    return (
        isinstance(counter, types.Array)
        and counter.dtype == types.int64
        and isinstance(index, types.Integer)
    )


def _slot_pointer(context: Any, builder: Any, signature: Any, args: Any) -> Any:
    """LLVM pointer to ``counter[index]`` (the intrinsics' first two arguments)."""
    aryty = signature.args[0]
    ary = context.make_array(aryty)(context, builder, args[0])
    return cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]])  # type: ignore[no-untyped-call]


def _fetch_add_typing(typingctx, counter, index):  # type: ignore[no-untyped-def]
    """Atomically add 1 to ``counter[index]`` (int64 array); returns the old
    value."""
    if not _is_int64_slot(counter, index):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw(
            "add", _slot_pointer(context, builder, signature, args), one, "seq_cst"
        )

    return types.int64(counter, index), codegen


_fetch_add: Any = intrinsic(_fetch_add_typing)


def _atomic_load_typing(typingctx, counter, index):  # type: ignore[no-untyped-def]
    """``counter[index]`` of an int64 array, read atomically (every read is
    a new load: a loop waiting on it sees another thread's store)."""
    if not _is_int64_slot(counter, index):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.load_atomic(_slot_pointer(context, builder, signature, args), "seq_cst", 8)

    return types.int64(counter, index), codegen


_atomic_load: Any = intrinsic(_atomic_load_typing)


def _atomic_store_typing(typingctx, counter, index, value):  # type: ignore[no-untyped-def]
    """``counter[index] = value`` on an int64 array, atomically and after
    every earlier write of this thread (sequentially consistent): a thread
    that reads the new value with :func:`_atomic_load` also sees those."""
    if not (_is_int64_slot(counter, index) and isinstance(value, types.Integer)):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        val = context.cast(builder, args[2], signature.args[2], types.int64)
        builder.store_atomic(val, _slot_pointer(context, builder, signature, args), "seq_cst", 8)
        return context.get_dummy_value()

    return types.void(counter, index, value), codegen


_atomic_store: Any = intrinsic(_atomic_store_typing)


@_jit
def publish(flags, index, value):  # type: ignore[no-untyped-def]
    """``flags[index] = value`` (int64 array) as :func:`_atomic_store`: for
    the calling thread to open a pass's gate or end its batches once all it
    wrote before is visible to the workers."""
    _atomic_store(flags, index, value)


@_jit
def _three_point(cm, c0, cp, method):  # type: ignore[no-untyped-def]
    """Sub-pixel offset of a peak from its samples left, centre and right
    (``method``: 1 sinc, 2 parabolic, 3 gaussian), and whether it is usable.

    sinc: Foroosh, Zerubia & Berthod (2002): the phase-correlation peak of a
    sub-pixel shift is a Dirichlet kernel, so a side sample over its sum with
    the centre gives the offset. parabolic and gaussian: the vertex of a
    parabola through the samples (gaussian: through their logarithms)."""
    off = 0.0
    if method == 1:
        right = cp >= cm
        side = cp if right else cm
        if side > 0:
            off = side / (side + c0)
        if not right:
            off = -off
    elif method == 2:
        den = cm - 2.0 * c0 + cp
        if den < 0:
            off = 0.5 * (cm - cp) / den
    else:
        lm = math.log(max(cm, 1e-12))
        l0 = math.log(max(c0, 1e-12))
        lp = math.log(max(cp, 1e-12))
        den = lm - 2.0 * l0 + lp
        if den < 0:
            off = 0.5 * (lm - lp) / den
    ok = math.isfinite(off) and abs(off) <= 1.0 and c0 > 0
    return (off if ok else 0.0), ok


@_jit
def subpixel_3pt(blocks, corr, method, scale, my, mx, sy, sx, out_fy, out_fx, out_ok):  # type: ignore[no-untyped-def]
    """Sub-pixel offsets of each block's integer peak ``(sy, sx)`` from the
    three samples around it along each axis (:func:`_three_point`), in the
    shifted correlation ``corr`` (shift ``-m`` at index 0; ``scale``: its
    value for identical blocks; ``corr[k]`` belongs to block ``blocks[k]``,
    the index of the other arrays). Neighbours beyond ``0..2m`` are clamped."""
    for k in range(blocks.size):
        i = blocks[k]
        cy = sy[i] + my
        cx = sx[i] + mx
        ym, yp = max(cy - 1, 0), min(cy + 1, 2 * my)
        xm, xp = max(cx - 1, 0), min(cx + 1, 2 * mx)
        c0 = np.float64(corr[k, cy, cx]) / scale
        fy, ok_y = _three_point(
            np.float64(corr[k, ym, cx]) / scale, c0, np.float64(corr[k, yp, cx]) / scale, method
        )
        fx, ok_x = _three_point(
            np.float64(corr[k, cy, xm]) / scale, c0, np.float64(corr[k, cy, xp]) / scale, method
        )
        out_fy[i] = fy
        out_fx[i] = fx
        out_ok[i] = ok_x and ok_y


#: Rows per FFTW call of :func:`forward_strips`' row transform (the plan
#: :class:`~afmdrift.registration._fftw.BatchedRealFFT` makes). The calls'
#: offsets into the strip arrays are multiples of ``32 · cols`` and ``64 ·
#: (cols // 2 + 1)`` bytes, so they keep the arrays' alignment modulo 16
#: bytes, which is what FFTW's new-array execute requires (FFTW manual,
#: "New-array Execute Functions").
STRIP_CHUNK = 8


@_jit
def forward_strips(  # type: ignore[no-untyped-def]
    grad, top, left, blocks, wy, wx, execute, plans, pointers, strip, strip_spec, spec, base
):
    """Spectra ``spec[k]`` (interleaved complex) of the windowed blocks
    ``grad[top[i]:top[i]+Ey, left[i]:left[i]+Ex] · wy ⊗ wx``, ``i =
    blocks[k]``, with the row transforms of overlapping windows done once.

    A 2-D real FFT is a real FFT of every row followed by a complex FFT of
    every column, and the window is a product ``wy(y) · wx(x)``: the
    transform of a row windowed by ``wx`` is the same in every window of the
    same columns, which only scales it by its ``wy``. Consecutive blocks
    with the same ``left`` whose rows meet form a run; each row of a run is
    windowed by ``wx`` into ``strip`` once and transformed,
    :data:`STRIP_CHUNK` rows per call
    (``plans[4]``), into ``strip_spec``; each block then takes its
    rows times ``wy`` into ``spec``, and one call (``plans[3]``) transforms
    the columns of all of them. With the engine's column-major batches and
    128² windows a block pitch of 50 px apart, this halves the row
    transforms (the larger part of a 2-D real FFT).

    ``execute``: FFTW's r2c and c2c execute functions; ``pointers[1]``,
    ``[3]``, ``[4]``: the addresses of ``spec``, ``strip`` and
    ``strip_spec`` (``strip`` holds at least ``len(blocks) · Ey +
    STRIP_CHUNK`` rows); ``base`` (scratch, ``len(blocks)``) receives each block's first
    row in the strip.
    """
    nb = blocks.size
    ey, ex = wy.size, wx.size
    half = strip_spec.shape[1] // 2
    filled = 0
    run_left = -1
    run_top = 0
    run_end = 0
    run_base = 0
    for k in range(nb):
        i = blocks[k]
        t = top[i]
        le = left[i]
        if k == 0 or le != run_left or t < run_top or t > run_end:
            run_left, run_top, run_end, run_base = le, t, t, filled
        for r in range(run_end, t + ey):
            src = grad[r, le : le + ex]
            dst = strip[run_base + r - run_top]
            for c in range(ex):
                dst[c] = src[c] * wx[c]
        run_end = max(run_end, t + ey)
        filled = run_base + run_end - run_top
        base[k] = run_base + t - run_top
    row_bytes = np.uint64(ex * 4)
    spec_row_bytes = np.uint64(half * 8)
    for c0 in range(0, filled, STRIP_CHUNK):
        r0 = np.uint64(c0)
        _fftw_execute(
            execute[0], plans[4], pointers[3] + r0 * row_bytes, pointers[4] + r0 * spec_row_bytes
        )
    for k in range(nb):
        for r in range(ey):
            src = strip_spec[base[k] + r]
            dst = spec[k, r]
            w = wy[r]
            for c in range(2 * half):
                dst[c] = src[c] * w
    _fftw_execute(execute[1], plans[3], pointers[1], pointers[1])


@_jit
def _measure_batch(a, b, kind, execute, thread, common):  # type: ignore[no-untyped-def]
    """Blocks ``order[a:b]`` through every step: window and forward FFT
    (:func:`forward_strips`), normalised cross-power spectrum, pruned
    inverse FFT, candidate peaks with their MSE check, sub-pixel offsets
    (``thread``, ``common``: see :func:`measure_batches`)."""
    plans, pointers, spec, corr, band, strip, strip_spec, base = thread
    (
        order, grad, top, left, wy, wx, w_rows, w_cols, w_vals, w_sum, eps_rel, floor,
        ky, kx, ref_conj, ref_band_mag, ramp, keep, cur_band_mag,
        search, npeaks, ratio, nms, ref_grad, ref_top, ref_left, inner, mse_rows, mse_cols,
        fy, fx, ramp_shift, envelope, method, scale,
        out_sy, out_sx, out_peak, out_mse, out_fx, out_fy, out_ok,
    ) = common  # fmt: skip
    nb = b - a
    blocks = order[a:b]
    forward_strips(
        grad, top, left, blocks, wy, wx, execute, plans[kind], pointers, strip,
        strip_spec, spec[:nb], base,
    )  # fmt: skip
    normalise_cross(
        blocks, spec[:nb], w_rows, w_cols, w_vals, w_sum, eps_rel, floor, ky, kx,
        ref_conj, ref_band_mag, ramp, keep, cur_band_mag, band[:nb] if band.shape[0] > 0 else band,
    )  # fmt: skip
    _fftw_execute(execute[1], plans[kind, 1], pointers[1], pointers[1])
    _fftw_execute(execute[2], plans[kind, 2], pointers[1], pointers[2])
    pick_peaks(
        blocks, corr[:nb], search, npeaks, ratio, nms, grad, ref_grad, ref_top, ref_left,
        top, left, inner, mse_rows, mse_cols, out_sy, out_sx, out_peak, out_mse,
    )  # fmt: skip
    if method == 0:
        dft_subpixel(
            blocks, band[:nb], fy, fx, out_sy, out_sx, ramp_shift, envelope,
            out_fx, out_fy, out_ok,
        )  # fmt: skip
    else:
        subpixel_3pt(
            blocks, corr[:nb], method, scale, ramp_shift[0], ramp_shift[1],
            out_sy, out_sx, out_fy, out_fx, out_ok,
        )  # fmt: skip


@_jit
def measure_batches(  # type: ignore[no-untyped-def]
    counter, gate, spins, starts, stops, kinds, execute, thread, common
):
    """One thread's share of a block pass, without the GIL: batches ``i``
    (blocks ``order[starts[i]:stops[i]]``, ``order`` the first of
    ``common``) taken in turn from the shared ``counter[0]`` (int64) until
    none is left, once ``gate[0]`` (int64) is no longer 0: a worker waits
    for the gate here, spinning without the GIL, while the calling thread
    completes the gradient image. Returns False, having taken no batch, if
    the gate is still closed after ``spins`` reads (the caller then waits
    for it another way); True once no batch is left.

    ``thread``: the thread's own FFTW plans and work arrays, ``(plans,
    pointers, spec, corr, band, strip, strip_spec, base)``:
    ``plans[kinds[i]]`` are the plans of
    :class:`afmdrift.registration._fftw.BatchedRealFFT` for batch ``i``'s
    size, all on the work arrays (room for the largest batch), whose
    addresses are ``pointers``; ``spec`` and ``strip_spec`` are spectra as
    interleaved float32, ``corr`` the inverse's output. ``execute``: FFTW's
    execute functions (see :class:`afmdrift.registration._fftw.Fftwf`).
    ``common``: the block order, then the arguments of
    :func:`forward_strips`, :func:`normalise_cross`, :func:`pick_peaks`,
    :func:`dft_subpixel` and :func:`subpixel_3pt` (``method``:
    :data:`SUBPIXEL_CODES`) that all threads share, in the order
    :class:`afmdrift.registration._engine.BlockEngine` builds them; their
    per-block arrays cover every block of the frame."""
    n = starts.size
    reads = 0
    while _atomic_load(gate, 0) == 0:
        reads += 1
        if reads > spins:
            return False
    while True:
        i = _fetch_add(counter, 0)
        if i >= n:
            return True
        _measure_batch(starts[i], stops[i], kinds[i], execute, thread, common)

"""Compiled kernels from the gradient image to the block spectra (Numba, no
GIL): the x-gradient pass with the frame checks' figures, each block's weight
centre, the windowed forward transform with shared row transforms, and the
mean removal, normalisation and cross-power of the spectra.

The per-block kernels work on one batch of blocks (``blocks``: the frame's
indices of the batch's entries). Complex spectra are passed as float32 views
with interleaved real and imaginary parts (``spectrum.view(np.float32)``:
shape ``(n, rows, 2 * (cols // 2 + 1))``), so that the loops are plain
float32 arithmetic the compiler vectorises (the normalisation and
cross-power loop compiles to packed square roots, divisions and products);
the reference spectra are interleaved int16 fixed point (see
:func:`normalise_reference`). All write into arrays the caller owns and
allocate only small scratch arrays.
"""

from __future__ import annotations

import math

import numpy as np

from afmdrift.registration._intrinsics import fftw_execute
from afmdrift.registration._jit import jit, jit_sums

__all__ = [
    "REF_SCALE",
    "STRIP_CHUNK",
    "forward_strips",
    "gradient_x",
    "normalise_cross",
    "normalise_reference",
    "weight_centroids",
]


@jit_sums
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


@jit_sums
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


@jit
def _remove_mean(c, spec, i):  # type: ignore[no-untyped-def]
    """Subtract block ``i``'s window-weighted mean: the window's DFT (a few
    non-zero terms ``c.w_vals`` at ``(c.w_rows, c.w_cols)``) times the mean.

    The zero frequency is then exactly zero by construction; it is set so,
    because the rounding left by the subtraction (large on height images
    with a big mean) would otherwise be normalised to unit magnitude and
    enter the correlation as one term of pure noise."""
    mean = spec[i, 0, 0] / c.w_sum
    for j in range(c.w_rows.size):
        r = c.w_rows[j]
        col = 2 * c.w_cols[j]
        spec[i, r, col] -= mean * c.w_vals[j, 0]
        spec[i, r, col + 1] -= mean * c.w_vals[j, 1]
    spec[i, 0, 0] = 0.0
    spec[i, 0, 1] = 0.0


@jit
def _floor(c, spec, i, abs2):  # type: ignore[no-untyped-def]
    """Magnitude floor of block ``i``: ``max(c.eps_rel · max|S|, c.floor)``;
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
    return np.float32(max(c.eps_rel * math.sqrt(peak2), c.floor))


@jit
def _band_row(r, rows, ky):  # type: ignore[no-untyped-def]
    """Band row (``ky = -ky_max .. +ky_max``) of spectrum row ``r``, or -1."""
    if r <= ky:
        return r + ky
    if r >= rows - ky:
        return r - (rows - ky)
    return -1


@jit
def _magnitudes(abs2, out):  # type: ignore[no-untyped-def]
    """``out[k] = sqrt(abs2[k])`` for the first ``out.size`` elements (the
    magnitudes of a spectrum row from its ``|S|²``)."""
    for k in range(out.size):
        out[k] = math.sqrt(abs2[k])


@jit
def _normalised(re, im, abs2, a):  # type: ignore[no-untyped-def]
    """``(re, im) / (|re + i im| + a)``, given ``abs2 = re² + im²``."""
    inv = np.float32(1.0) / (np.float32(math.sqrt(abs2)) + a)
    return re * inv, im * inv


#: Fixed-point scale of the stored reference spectra: components of
#: ``conj(Ŝ) · ramp`` (magnitude below 1) as int16 multiples of 1 / 32767.
REF_SCALE = 32767.0


@jit
def _to_fixed(x):  # type: ignore[no-untyped-def]
    """``x`` (|x| ≤ 1) to int16 multiples of ``1 / REF_SCALE``, rounded."""
    return np.int16(x * np.float32(REF_SCALE) + (np.float32(0.5) if x >= 0 else np.float32(-0.5)))


@jit
def _reference_row(s, abs2, ramp, o, a):  # type: ignore[no-untyped-def]
    """``o = conj(s / (|s| + a)) · ramp`` over an interleaved complex row
    (``abs2``: its ``|s|²``), in fixed point (int16, see :data:`REF_SCALE`)."""
    for k in range(s.size // 2):
        re, im = _normalised(s[2 * k], s[2 * k + 1], abs2[k], a)
        o[2 * k] = _to_fixed(re * ramp[2 * k] + im * ramp[2 * k + 1])
        o[2 * k + 1] = _to_fixed(re * ramp[2 * k + 1] - im * ramp[2 * k])


@jit
def normalise_reference(c, blocks, spec, out, band_mag):  # type: ignore[no-untyped-def]
    """Reference spectra: remove each block's weighted mean from ``spec`` (in
    place), write ``out = conj(S / (|S| + a)) · ramp`` and ``band_mag = |S|``
    in the sub-pixel band (rows ``-ky..ky``, columns ``0..kx``).

    The phase ramp ``exp(-2πi k·m)`` (``c.ramp``: one block's spectrum shape)
    shifts every correlation by ``m``, the search radius, so that shifts
    ``-m..m`` come out of the inverse FFT as rows and columns ``0..2m``.

    ``c``: :class:`~afmdrift.registration._constants.SpectrumConstants`.
    ``spec[k]`` belongs to block ``blocks[k]``, the index of ``out`` and
    ``band_mag``. spec : (len(blocks), rows, 2·half) float32 (interleaved
    complex); out : (n, rows, 2·half) int16 (interleaved); band_mag : (n,
    2·ky + 1, kx + 1) float32.
    """
    rows = spec.shape[1]
    abs2 = np.empty((rows, spec.shape[2] // 2), dtype=np.float32)
    for k in range(blocks.size):
        i = blocks[k]
        _remove_mean(c, spec, k)
        a = _floor(c, spec, k, abs2)
        for r in range(rows):
            b = _band_row(r, rows, c.ky)
            if b >= 0:
                _magnitudes(abs2[r], band_mag[i, b])
            _reference_row(spec[k, r], abs2[r], c.ramp[r], out[i, r], a)


@jit
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


@jit
def normalise_cross(c, blocks, spec, ref, ref_band_mag, keep, band_mag, band):  # type: ignore[no-untyped-def]
    """Current spectra against a reference, in one pass per block.

    Removes each block's window-weighted mean from ``spec`` and turns it in
    place into the normalised cross-power spectrum ``Ŝ · ref`` with
    ``Ŝ = S / (|S| + a)`` and ``ref`` the reference's ``conj(R̂) · ramp``
    (see :func:`normalise_reference`; int16): the input of the inverse FFT.
    Also writes ``band_mag = |S|`` in the sub-pixel band; if ``keep`` has
    blocks, ``keep = conj(Ŝ) · ramp`` in the reference's int16 form (the
    frame is to become the next reference);
    and, if ``band`` has blocks, the weighted band ``band = Ŝ · ref · |S| ·
    |R|`` of the ``dft`` sub-pixel method. ``spec``, ``ref``, ``keep`` and
    ``band`` are interleaved complex (``ref`` and ``keep`` int16, the others
    float32). ``c``:
    :class:`~afmdrift.registration._constants.SpectrumConstants`.
    ``spec[k]`` and ``band[k]`` belong to block ``blocks[k]``, the index of
    ``ref``, ``ref_band_mag``, ``keep`` and ``band_mag``.
    """
    n, rows = blocks.size, spec.shape[1]
    ky, kx = c.ky, c.kx
    keeping = keep.shape[0] > 0
    with_band = band.shape[0] > 0
    abs2 = np.empty((rows, spec.shape[2] // 2), dtype=np.float32)
    for k in range(n):
        i = blocks[k]
        _remove_mean(c, spec, k)
        a = _floor(c, spec, k, abs2)
        for r in range(rows):
            s = spec[k, r]
            b = _band_row(r, rows, ky)
            if b >= 0:
                _magnitudes(abs2[r], band_mag[i, b])
            if keeping:
                _reference_row(s, abs2[r], c.ramp[r], keep[i, r], a)
            _cross_row(s, abs2[r], ref[i, r], a)
            if b >= 0 and with_band:
                for col in range(kx + 1):
                    w = band_mag[i, b, col] * ref_band_mag[i, b, col]
                    band[k, b, 2 * col] = s[2 * col] * w
                    band[k, b, 2 * col + 1] = s[2 * col + 1] * w


#: Rows per FFTW call of :func:`forward_strips`' row transform (the plan
#: :class:`~afmdrift.registration._fftw.BatchedRealFFT` makes). The calls'
#: offsets into the strip arrays are multiples of ``32 · cols`` and ``64 ·
#: (cols // 2 + 1)`` bytes, so they keep the arrays' alignment modulo 16
#: bytes, which is what FFTW's new-array execute requires (FFTW manual,
#: "New-array Execute Functions").
STRIP_CHUNK = 8


@jit
def forward_strips(t, cur, blocks, plans, work):  # type: ignore[no-untyped-def]
    """Spectra ``work.spec[k]`` (interleaved complex) of the windowed blocks
    ``cur.grad[top:top+Ey, left:left+Ex] · wy ⊗ wx`` at the corners
    ``cur.top[i]``, ``cur.left[i]``, ``i = blocks[k]``, with the row
    transforms of overlapping windows done once.

    A 2-D real FFT is a real FFT of every row followed by a complex FFT of
    every column, and the window is a product ``wy(y) · wx(x)``: the
    transform of a row windowed by ``wx`` is the same in every window of the
    same columns, which only scales it by its ``wy``. Consecutive blocks
    with the same ``left`` whose rows meet form a run; each row of a run is
    windowed by ``wx`` into ``work.strip`` once and transformed,
    :data:`STRIP_CHUNK` rows per call
    (``plans[4]``), into ``work.strip_spec``; each block then takes its
    rows times ``wy`` into ``work.spec``, and one call (``plans[3]``)
    transforms the columns of all of them. With the engine's column-major
    batches and 128² windows a block pitch of 50 px apart, this halves the
    row transforms (the larger part of a 2-D real FFT).

    ``t``: :class:`~afmdrift.registration._constants.TransformConstants`
    (``wy``, ``wx`` and FFTW's r2c and c2c execute functions); ``cur``: a
    :class:`~afmdrift.registration._passes.Windows`; ``plans``: the FFTW
    plans of :class:`~afmdrift.registration._fftw.BatchedRealFFT` for
    ``len(blocks)`` blocks on ``work``, a
    :class:`~afmdrift.registration._passes.ThreadWork` (its ``strip`` holds
    at least ``len(blocks) · Ey + STRIP_CHUNK`` rows; its ``base``, scratch,
    receives each block's first row in the strip).
    """
    nb = blocks.size
    wy, wx = t.wy, t.wx
    ey, ex = wy.size, wx.size
    grad, top, left = cur.grad, cur.top, cur.left
    strip, strip_spec, spec, base = work.strip, work.strip_spec, work.spec, work.base
    half = strip_spec.shape[1] // 2
    filled = 0
    run_left = -1
    run_top = 0
    run_end = 0
    run_base = 0
    for k in range(nb):
        i = blocks[k]
        t0 = top[i]
        le = left[i]
        if k == 0 or le != run_left or t0 < run_top or t0 > run_end:
            run_left, run_top, run_end, run_base = le, t0, t0, filled
        for r in range(run_end, t0 + ey):
            src = grad[r, le : le + ex]
            dst = strip[run_base + r - run_top]
            for c in range(ex):
                dst[c] = src[c] * wx[c]
        run_end = max(run_end, t0 + ey)
        filled = run_base + run_end - run_top
        base[k] = run_base + t0 - run_top
    row_bytes = np.uint64(ex * 4)
    spec_row_bytes = np.uint64(half * 8)
    pointers = work.pointers
    for c0 in range(0, filled, STRIP_CHUNK):
        r0 = np.uint64(c0)
        fftw_execute(
            t.execute[0], plans[4], pointers[3] + r0 * row_bytes, pointers[4] + r0 * spec_row_bytes
        )
    for k in range(nb):
        for r in range(ey):
            src = strip_spec[base[k] + r]
            dst = spec[k, r]
            w = wy[r]
            for c in range(2 * half):
                dst[c] = src[c] * w
    fftw_execute(t.execute[1], plans[3], pointers[1], pointers[1])

"""A block pass (Numba, no GIL): the window placement, one thread's share of
the batches with every step (FFTs included) in one compiled call, and the
assembly of the block vectors.

Results do not depend on the thread count: every block is computed on its
own, in a fixed order, and the split into batches is fixed by the frame
layout.
"""

from __future__ import annotations

import numpy as np

from afmdrift.registration._intrinsics import atomic_load, fetch_add, fftw_execute
from afmdrift.registration._jit import jit
from afmdrift.registration._kernels import masked_medians
from afmdrift.registration._peaks import pick_peaks
from afmdrift.registration._spectra import forward_strips, normalise_cross
from afmdrift.registration._subpixel import dft_subpixel, subpixel_3pt

__all__ = ["assemble", "measure_batches", "place_windows"]


@jit
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


@jit
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


@jit
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
    fftw_execute(execute[1], plans[kind, 1], pointers[1], pointers[1])
    fftw_execute(execute[2], plans[kind, 2], pointers[1], pointers[2])
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


@jit
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
    while atomic_load(gate, 0) == 0:
        reads += 1
        if reads > spins:
            return False
    while True:
        i = fetch_add(counter, 0)
        if i >= n:
            return True
        _measure_batch(starts[i], stops[i], kinds[i], execute, thread, common)

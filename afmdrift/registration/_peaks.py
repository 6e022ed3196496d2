"""Compiled peak search of the block pass (Numba, no GIL): the top-K maxima of
each block's correlation with non-maximum suppression, each verified by the
mean squared difference of the blocks at its shift.
"""

from __future__ import annotations

import numpy as np

from afmdrift.registration._jit import jit, jit_finite

__all__ = ["pick_peaks"]


@jit_finite
def _row_max(row, x0, x1):  # type: ignore[no-untyped-def]
    """Highest value of ``row[x0..x1]`` (finite values)."""
    m = row[x0]
    for c in range(x0, x1 + 1):
        m = max(m, row[c])
    return m


@jit
def _suppressed(iy, ix, acc_y, acc_x, n_acc, nms):  # type: ignore[no-untyped-def]
    """Whether ``(iy, ix)`` lies in the square of half-size ``nms`` around
    one of the ``n_acc`` accepted peaks."""
    for q in range(n_acc):  # noqa: SIM110 (a generator in any() does not compile)
        if abs(iy - acc_y[q]) <= nms and abs(ix - acc_x[q]) <= nms:
            return True
    return False


@jit
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


@jit
def _first_column(row, iy, x0, x1, value, acc_y, acc_x, n_acc, nms):  # type: ignore[no-untyped-def]
    """First column of ``row[x0..x1]`` holding ``value`` outside the
    suppressed squares."""
    for ix in range(x0, x1 + 1):
        if row[ix] == value and not _suppressed(iy, ix, acc_y, acc_x, n_acc, nms):
            return ix
    return x0


@jit
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


@jit
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

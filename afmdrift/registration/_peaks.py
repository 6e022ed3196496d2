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
def pick_peaks(c, blocks, corr, search, cur, ref, out):  # type: ignore[no-untyped-def]
    """Top-K correlation peaks per block, verified by MSE.

    ``corr[k, iy, ix]`` is block ``blocks[k]``'s correlation at the shift
    ``(iy - my, ix - mx)`` (rows and columns ``0..2m``; ``search = (ry, rx,
    my, mx)``). Searches shifts within ``±(ry, rx)`` (``ry ≤ my``, ``rx ≤
    mx``) for up to ``c.peaks`` maxima, greedily, each at least ``c.nms`` px
    (per axis) from the previous ones; a peak is a candidate while it is
    positive and at least ``c.ratio`` of the block's highest. Each candidate
    is verified by :func:`_block_mse` of the inner blocks (``c.inner = (iy0,
    ix0)`` offset in the window) at the total shift ``window move + peak``;
    the lowest MSE wins (the first on ties; with no candidate, the highest
    peak and ``inf``). Ties between equal correlation values go to the first
    in row-major order of the region.

    ``c``: :class:`~afmdrift.registration._constants.PeakConstants`; ``cur``
    and ``ref``: the current and reference gradient images with their
    window corners (:class:`~afmdrift.registration._passes.Windows`), indexed
    by ``blocks[k]`` as the outputs are. Writes, per block, into ``out`` (a
    :class:`~afmdrift.registration._passes.Peaks`): the integer shift ``sy``,
    ``sx``, the unnormalised correlation value ``peak`` and ``mse``. The
    search rows' maxima are found once; after each accepted peak only the
    rows its suppressed square covers are scanned again, and the column of a
    peak is looked up only in the row that wins.
    """
    ry, rx, my, mx = search[0], search[1], search[2], search[3]
    y0r, x0r, x1r = my - ry, mx - rx, mx + rx
    row_best = np.empty(2 * ry + 1, dtype=np.float32)
    accepted = (np.empty(c.peaks, dtype=np.intp), np.empty(c.peaks, dtype=np.intp))
    for k in range(blocks.size):
        i = blocks[k]
        for h in range(row_best.size):
            row_best[h] = _row_max(corr[k, y0r + h], x0r, x1r)
        best_y, best_x, best_v, best_mse = _best_candidate(
            c, corr[k], search, row_best, accepted, cur, ref, i
        )
        out.sy[i] = best_y - my
        out.sx[i] = best_x - mx
        out.peak[i] = best_v
        out.mse[i] = best_mse


@jit
def _best_candidate(c, corr, search, row_best, accepted, cur, ref, i):  # type: ignore[no-untyped-def]
    """Block ``i``'s verified peak in its correlation ``corr`` (see
    :func:`pick_peaks`), given the search rows' maxima ``row_best`` (updated
    as peaks are suppressed; ``accepted``: scratch for the accepted peaks'
    rows and columns): its row and column in ``corr``, value and MSE."""
    ry, rx, my, mx = search[0], search[1], search[2], search[3]
    y0r, x0r, x1r = my - ry, mx - rx, mx + rx
    height = row_best.size
    acc_y, acc_x = accepted
    nms = c.nms
    first = -np.inf
    best_mse = np.inf
    best_y = 0
    best_x = 0
    best_v = -np.inf
    for j in range(c.peaks):
        v = -np.inf
        hy = -1
        for h in range(height):
            if row_best[h] > v:
                v = row_best[h]
                hy = h
        if hy < 0:
            break
        py = y0r + hy
        px = _first_column(corr[py], py, x0r, x1r, v, acc_y, acc_x, j, nms)
        if j == 0:
            first = v
            best_y, best_x, best_v = py, px, v
        if not (v > 0 and v >= c.ratio * first):
            break  # later peaks are lower: no candidates either
        mse = _block_mse(
            cur.grad,
            ref.grad,
            ref.top[i] + c.inner[0],
            ref.left[i] + c.inner[1],
            (cur.top[i] - ref.top[i]) + (py - my),
            (cur.left[i] - ref.left[i]) + (px - mx),
            c.mse_rows,
            c.mse_cols,
        )
        if mse < best_mse:
            best_mse = mse
            best_y, best_x, best_v = py, px, v
        acc_y[j] = py
        acc_x[j] = px
        if j + 1 < c.peaks:
            for h in range(max(0, hy - nms), min(height, hy + nms + 1)):
                row_best[h] = _row_max_masked(
                    corr[y0r + h], y0r + h, x0r, x1r, acc_y, acc_x, j + 1, nms
                )
    return best_y, best_x, best_v, best_mse

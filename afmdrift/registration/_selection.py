"""Compiled block-selection statistics (Numba, no GIL): which blocks are
usable, the outlier rules (the iterated median/MAD rule and the paper's),
the trend rule over the block rows, and the masked means, deviations,
medians and row means of the block vectors; with the records of the rules'
settings. The one selection path that uses them is
:func:`afmdrift.registration._outliers.select_blocks`.

They work on the whole frame's blocks and allocate only small scratch
arrays.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.registration._jit import jit

__all__ = [
    "MadRule",
    "RowMeans",
    "SelectionRule",
    "TrendRule",
    "masked_mean_std",
    "masked_medians",
    "reject_mad",
    "reject_paper",
    "row_groups",
    "row_means",
    "select_blocks",
    "trend_select",
    "usable_blocks",
]


class MadRule(NamedTuple):
    """The iterated per-axis median/MAD rule (:func:`reject_mad`)."""

    #: Largest robust z-score kept.
    threshold: float
    #: Smallest robust scale (px).
    floor: float
    #: Most rounds.
    max_iter: int


class TrendRule(NamedTuple):
    """The trend over the block rows (:func:`trend_select`)."""

    #: Highest degree of the per-axis polynomial in the row.
    max_degree: int
    #: F statistic above which the trend is preferred to one mean, and the
    #: smallest share of the one mean's residual sum of squares it must explain.
    f_min: float
    explained_min: float


class SelectionRule(NamedTuple):
    """Which blocks are usable and which outlier rule judges them
    (:func:`select_blocks`)."""

    #: Placed blocks needed before clamped ones are used too (tiny frames).
    min_blocks: int
    #: The MAD rule (``mad``) if True, else the paper's rule (``epsilon`` px
    #: from the mean vector).
    mad: bool
    mad_rule: MadRule
    epsilon: float


class RowMeans(NamedTuple):
    """Outputs of :func:`row_means`, ``(n,)`` and ``(n, 2)`` float64; the
    first entries are written."""

    levels: npt.NDArray[np.float64]
    counts: npt.NDArray[np.float64]
    means: npt.NDArray[np.float64]
    at: npt.NDArray[np.float64]


@jit
def _gather(vectors, mask, axis, out):  # type: ignore[no-untyped-def]
    """Copy column ``axis`` of the rows of ``vectors`` where ``mask`` to the
    start of ``out``; returns their number."""
    m = 0
    for i in range(vectors.shape[0]):
        if mask[i]:
            out[m] = vectors[i, axis]
            m += 1
    return m


@jit
def reject_mad(vectors, keep, rule, out):  # type: ignore[no-untyped-def]
    """Iterated per-axis median/MAD outlier rule (see
    :mod:`afmdrift.registration._outliers`): ``out`` starts as ``keep``;
    while at least 3 blocks remain, blocks of ``keep`` whose robust z-score
    ``|v - median| / (1.4826 · max(MAD, floor))`` exceeds ``threshold`` on
    either axis are dropped, until nothing changes (at most ``max_iter``
    rounds; ``rule``: a :class:`MadRule`). Returns the number kept.

    vectors : (n, 2) float64; keep, out : (n,) bool.
    """
    threshold, floor, max_iter = rule
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


@jit
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


@jit
def _poly_residual(x, vectors, coef, degree, residual):  # type: ignore[no-untyped-def]
    for i in range(x.shape[0]):
        for j in range(2):
            s = 0.0
            p_k = 1.0
            for k in range(degree + 1):
                s += coef[k, j] * p_k
                p_k *= x[i]
            residual[i, j] = vectors[i, j] - s


@jit
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


@jit
def row_means(valid, vectors, row_px, weight_row_px, out):  # type: ignore[no-untyped-def]
    """The ``valid`` blocks grouped by their row (:func:`row_groups`), into
    the starts of the outputs (a :class:`RowMeans`): the distinct rows
    ``levels`` and, per row, the number of its blocks, their mean vector and
    the mean of their ``weight_row_px`` (each sum in block order). Returns
    ``(valid blocks, rows)``.

    valid : (n,) bool; vectors : (n, 2) float64; row_px, weight_row_px : (n,)
    float64.
    """
    levels, counts, means, at = out
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


@jit
def trend_select(vectors, row_px, usable, mad, trend, out):  # type: ignore[no-untyped-def]
    """The trend rule of :func:`afmdrift.registration._trend.select_by_trend`
    (see there), in one compiled pass: per-row medians, a weighted polynomial
    of degree up to ``trend.max_degree`` through them, the MAD rule ``mad``
    on the residuals (:func:`reject_mad`), refitted on the kept blocks and
    judged once more; the spreads and the F test of the trend against one
    mean (``trend``: a :class:`TrendRule`).

    vectors : (n, 2) float64; row_px : (n,) float64; usable, out : (n,) bool.
    Returns ``(n_valid, spread_x, spread_y, significant)``.
    """
    max_degree, f_min, explained_min = trend
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
        good = reject_mad(residual, usable, mad, out)
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
    noise = max(rss_sum / (2 * dof), (mad.floor / 2) ** 2)
    explained = 1.0 - rss_sum / max(rss0_sum, 1e-300)
    significant = gain / noise > f_min and explained >= explained_min
    return good, math.sqrt(rss[0] / dof), math.sqrt(rss[1] / dof), significant


@jit
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


@jit
def select_blocks(vectors, measured, placed, in_overlap, rule, usable, valid, stats):  # type: ignore[no-untyped-def]
    """The frame's valid blocks in one call (``rule``: a
    :class:`SelectionRule`): :func:`usable_blocks` into ``usable``, then the
    outlier rule (:func:`reject_mad` if ``rule.mad``, else
    :func:`reject_paper`) into ``valid``, then :func:`masked_mean_std`
    (sample deviation) of the valid blocks into ``stats``. Returns
    ``(available, valid count)``."""
    available = usable_blocks(measured, placed, in_overlap, rule.min_blocks, usable)
    if rule.mad:
        n_valid = reject_mad(vectors, usable, rule.mad_rule, valid)
    else:
        n_valid = reject_paper(vectors, usable, rule.epsilon, valid)
    masked_mean_std(vectors, valid, 1, stats)
    return available, n_valid


@jit
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


@jit
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


@jit
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

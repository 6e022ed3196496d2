"""Block selection that allows the drift to change while the frame is scanned.

A frame's rows are scanned one after another (512 rows at 4 Hz take 128 s),
so a block vector measures the drift between the scan times of *its* rows in
the two frames, and block rows scanned at other times see other drifts. When
the drift speeds up or slows down during the scan (warm-up, creep after an
offset move, an air-conditioning cycle) the vectors of the top and bottom
block rows differ by pixels, and a rule that wants all blocks to agree with
one mean rejects exactly the frames where the drift is fastest.

:func:`select_by_trend` instead judges each block by its residual from a
smooth trend of the block vectors over the block rows (a polynomial in the
row, per axis, of degree up to ``TREND_DEGREE``), fitted robustly:

1. per block row, the median of the usable blocks (robust within a row);
2. a weighted polynomial through those medians (weights: blocks per row);
3. the iterated median/MAD rule (:func:`afmdrift.registration._kernels.reject_mad`)
   on the residual vectors;
4. the polynomial refitted by least squares on the blocks kept, and step 3
   repeated once on the new residuals.

The frame's spread is the sample standard deviation of the residuals of the
valid blocks (degrees of freedom: valid blocks minus trend coefficients).
Where all block rows agree the trend is flat and this is the constant model
of the ``mad`` rule, within rounding.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from afmdrift.registration import _kernels

__all__ = ["TREND_DEGREE", "TREND_EXPLAINED", "TREND_F", "select_by_trend"]

#: F statistic above which the trend is preferred to one mean (about the
#: 0.1 % point of F(4, 60): a uniform shift almost never passes it).
TREND_F = 10.0
#: Smallest share of the one-mean residual sum of squares the trend must
#: explain: a trend that is significant but leaves most of the scatter is
#: texture-correlated error of the blocks (quantised high-speed AFM frames),
#: not the drift changing during the scan.
TREND_EXPLAINED = 0.5
#: Highest degree of the per-axis trend over the block rows (a quadratic
#: follows an exponential warm-up or a logarithmic creep over one frame to
#: well below the sub-pixel noise of a block).
TREND_DEGREE = 2


def _design(rows: npt.NDArray[np.float64], degree: int) -> npt.NDArray[np.float64]:
    return np.vander(rows, degree + 1, increasing=True)


def _fit(
    rows: npt.NDArray[np.float64],
    values: npt.NDArray[np.float64],
    weights: npt.NDArray[np.float64],
    degree: int,
) -> npt.NDArray[np.float64]:
    """Weighted least-squares polynomial coefficients, shape (degree + 1, 2)."""
    a = _design(rows, degree)
    aw = a * weights[:, None]
    # normal equations of a (degree + 1)-column problem: a 3×3 solve at most
    # (rows are scaled to [-1, 1], so the system is well conditioned)
    try:
        coef = np.linalg.solve(aw.T @ a, aw.T @ values)
    except np.linalg.LinAlgError:
        coef, *_ = np.linalg.lstsq(a * np.sqrt(weights)[:, None],
                                   values * np.sqrt(weights)[:, None], rcond=None)  # fmt: skip
    return np.asarray(coef, dtype=np.float64)


def _group_medians(
    vec: npt.NDArray[np.float64], group: npt.NDArray[np.intp], n_groups: int
) -> npt.NDArray[np.float64]:
    """Per-group, per-axis medians of ``vec`` (n, 2), groups 0..n_groups-1 all
    non-empty: one sort per axis instead of a mask and a median per group."""
    counts = np.bincount(group, minlength=n_groups)
    start = np.concatenate(([0], np.cumsum(counts)[:-1]))
    lo, hi = start + (counts - 1) // 2, start + counts // 2
    out = np.empty((n_groups, 2))
    for axis in (0, 1):
        v = vec[np.lexsort((vec[:, axis], group)), axis]
        out[:, axis] = 0.5 * (v[lo] + v[hi])
    return out


def select_by_trend(
    vectors_px: npt.NDArray[np.float64],
    row_px: npt.NDArray[np.float64],
    usable: npt.NDArray[np.bool_],
    *,
    threshold: float,
    floor_px: float,
    max_iter: int,
    out: npt.NDArray[np.bool_],
) -> tuple[int, float, float, bool]:
    """Valid blocks judged by their residual from a smooth trend over the rows.

    Parameters
    ----------
    vectors_px : ndarray, shape (n, 2)
        Block vectors ``(dx, dy)``, px.
    row_px : ndarray, shape (n,)
        Row of each block's centre in the reference frame, px.
    usable : ndarray of bool, shape (n,)
        Blocks that may be valid.
    threshold, floor_px, max_iter
        Parameters of the median/MAD rule (see :mod:`._outliers`).
    out : ndarray of bool, shape (n,)
        Receives the valid blocks.

    Returns
    -------
    (n_valid, spread_x_px, spread_y_px, significant)
        Spreads are the residual standard deviations (NaN below
        ``degree + 2`` valid blocks); ``significant`` when the trend explains
        the kept blocks better than one mean (F statistic above
        :data:`TREND_F`, the residual noise floored at half the MAD floor, and
        at least :data:`TREND_EXPLAINED` of their scatter explained).
    """
    out[:] = usable
    idx = np.nonzero(usable)[0]
    if idx.size < 3:
        return int(idx.size), float("nan"), float("nan"), False
    rows = row_px[idx]
    levels, inverse = np.unique(rows, return_inverse=True)
    degree = min(TREND_DEGREE, levels.size - 1, max(0, (idx.size - 2) // 3))
    scale = max(float(np.ptp(levels)), 1.0)
    centre = float(levels.mean())
    x_rows = (row_px - centre) / scale
    vec = vectors_px[idx]
    medians = _group_medians(vec, inverse, levels.size)
    counts = np.bincount(inverse, minlength=levels.size).astype(np.float64)
    coef = _fit((levels - centre) / scale, medians, counts, degree)
    design = _design(x_rows, degree)
    residual = np.ascontiguousarray(vectors_px - design @ coef)
    keep = np.ascontiguousarray(usable)
    for _ in range(2):
        _kernels.reject_mad(residual, keep, threshold, floor_px, max_iter, out)
        good = np.nonzero(out)[0]
        if good.size < degree + 2:
            break
        coef = _fit(x_rows[good], vectors_px[good], np.ones(good.size), degree)
        residual = np.ascontiguousarray(vectors_px - design @ coef)
    good = np.nonzero(out)[0]
    dof = good.size - (degree + 1)
    if dof < 1 or degree == 0:
        return int(good.size), float("nan"), float("nan"), False
    r = residual[good]
    rss = np.sum(r * r, axis=0)
    spread = np.sqrt(rss / dof)
    # F-test of the trend against one mean on the same blocks, both axes pooled.
    v = vectors_px[good]
    rss0 = np.sum((v - v.mean(axis=0)) ** 2, axis=0)
    gain = float(np.sum(rss0 - rss)) / (2 * degree)
    noise = max(float(np.sum(rss)) / (2 * dof), (floor_px / 2) ** 2)
    explained = 1.0 - float(np.sum(rss)) / max(float(np.sum(rss0)), 1e-300)
    significant = gain / noise > TREND_F and explained >= TREND_EXPLAINED
    return int(good.size), float(spread[0]), float(spread[1]), significant

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
3. the iterated median/MAD rule (:func:`afmdrift.registration._selection.reject_mad`)
   on the residual vectors;
4. the polynomial refitted by least squares on the blocks kept, and step 3
   repeated once on the new residuals.

One compiled pass (:func:`afmdrift.registration._selection.trend_select`) does
it all: the rule runs on every frame, and as NumPy calls on a few dozen
blocks it cost more than the block engine's own post-processing.

The frame's spread is the sample standard deviation of the residuals of the
valid blocks (degrees of freedom: valid blocks minus trend coefficients).
Where all block rows agree the trend is flat and this is the constant model
of the ``mad`` rule, within rounding.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from afmdrift.registration._selection import MadRule, TrendRule, trend_select

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

_TREND = TrendRule(max_degree=TREND_DEGREE, f_min=TREND_F, explained_min=TREND_EXPLAINED)


def select_by_trend(
    vectors_px: npt.NDArray[np.float64],
    row_px: npt.NDArray[np.float64],
    usable: npt.NDArray[np.bool_],
    *,
    rule: MadRule,
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
    rule : MadRule
        The median/MAD rule (see :mod:`._outliers`).
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
    n_valid, spread_x, spread_y, significant = trend_select(
        vectors_px, row_px, usable, rule, _TREND, out
    )
    return int(n_valid), float(spread_x), float(spread_y), bool(significant)

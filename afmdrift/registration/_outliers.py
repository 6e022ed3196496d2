"""Block selection: which measured blocks are valid, and their mean and
spread. :func:`select_blocks` is the one path (``combine`` in
:mod:`afmdrift.registration._measure` takes the frame's drift from it).

Usable blocks are those measured whose windows sit where their content is
expected (``placed``); in frames so small that fewer than
``min_valid_blocks`` of those exist, every measured block. Among them, two
rules (``RegistrationConfig.outlier_rule``):

``"paper"``
    Yang et al. (2008): compute the mean vector of the usable blocks and
    drop every block farther than ``epsilon_px`` (Euclidean) from it; one pass.
    Simple, but the mean itself is pulled by the outliers, so with many
    altered blocks good blocks can be dropped and bad ones kept.
``"mad"`` (default)
    Iterated median/MAD: per axis, robust z = |v − median| / (1.4826·MAD),
    with the MAD floored at ``MAD_FLOOR_PX`` so that near-identical vectors
    are not split by rounding noise; drop blocks with z > ``mad_threshold``
    on either axis and repeat on the survivors until nothing changes. The
    blocks are also judged by their residual from a smooth trend over the
    block rows (:func:`afmdrift.registration._trend.select_by_trend`), which
    are scanned at different times.

The rules are compiled (:mod:`afmdrift.registration._selection`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.registration import _selection
from afmdrift.registration._selection import MadRule, SelectionRule
from afmdrift.registration._trend import select_by_trend

__all__ = ["MAD_FLOOR_PX", "MAX_ITER", "Selection", "needed_blocks", "select_blocks"]

#: Smallest robust scale (px): sub-pixel estimator noise well below this is
#: not evidence of a different motion.
MAD_FLOOR_PX = 0.05
#: Most rounds of the MAD rule.
MAX_ITER = 20


class Selection(NamedTuple):
    """The valid blocks of a frame, ``(n,)``, their number, the number of
    blocks a valid result counts from (``available``: see
    :func:`needed_blocks`), and the mean ``(x, y)`` and spread ``(x, y)`` of
    the valid blocks' vectors, px: the sample standard deviation, or with the
    trend the residual deviation about it (NaN where undefined)."""

    valid: npt.NDArray[np.bool_]
    n_valid: int
    available: int
    mean_px: tuple[float, float]
    spread_px: tuple[float, float]


def needed_blocks(config: RegistrationConfig, available: int) -> int:
    """Valid blocks a result needs: ``min_valid_blocks``, and at least
    ``min_valid_fraction`` of the ``available`` blocks."""
    return max(config.min_valid_blocks, math.ceil(config.min_valid_fraction * available))


def select_blocks(
    vectors_px: npt.NDArray[np.float64],
    measured: npt.NDArray[np.bool_],
    placed: npt.NDArray[np.bool_],
    in_overlap: npt.NDArray[np.bool_],
    *,
    row_px: npt.NDArray[np.float64],
    config: RegistrationConfig,
    textured: npt.NDArray[np.bool_] | None = None,
) -> Selection:
    """The valid blocks by ``config.outlier_rule`` (see the module docstring).

    Parameters
    ----------
    vectors_px : ndarray, shape (n, 2)
        Block vectors ``(dx, dy)``, px (float64).
    measured, placed, in_overlap : ndarray of bool, shape (n,)
        Blocks with a usable peak; windows placed without clamping; windows
        clamped by at most half the search radius (the fallback's
        ``available`` blocks).
    row_px : ndarray, shape (n,)
        Row of each block's centre in the reference frame, px (the trend).
    config : RegistrationConfig
        ``outlier_rule``, ``mad_threshold``, ``epsilon_px``,
        ``min_valid_blocks``, ``min_valid_fraction`` and
        ``max_block_spread_px``.
    textured : ndarray of bool, shape (n,), optional
        Blocks whose reference content stands out of the noise; with the
        MAD rule only they count among the ``available`` blocks.

    Returns
    -------
    Selection
    """
    mad = MadRule(threshold=config.mad_threshold, floor=MAD_FLOOR_PX, max_iter=MAX_ITER)
    rule = SelectionRule(
        min_blocks=config.min_valid_blocks,
        mad=config.outlier_rule == "mad",
        mad_rule=mad,
        epsilon=config.epsilon_px,
    )
    usable, valid = np.empty_like(measured), np.empty_like(measured)
    stats = np.empty(4)
    # Prefer blocks whose windows sit where their content is expected (fall
    # back to clamped windows only when too few are left: tiny frames), drop
    # the outliers, and take the mean (x, y) and sample standard deviation
    # (x, y) of the valid blocks: one compiled call.
    available, n_valid = _selection.select_blocks(
        vectors_px, measured, placed, in_overlap, rule, usable, valid, stats
    )
    mean_x, mean_y, spread_x, spread_y = (float(v) for v in stats)
    one_mean = Selection(
        valid, int(n_valid), int(available), (mean_x, mean_y), (spread_x, spread_y)
    )
    if not rule.mad:
        return one_mean
    if textured is not None:
        # the same blocks usable_blocks counted (placed, or in the overlap
        # in its fallback for tiny frames), less the featureless ones
        placed_ok = int(np.count_nonzero(measured & placed)) >= config.min_valid_blocks
        base = placed if placed_ok else in_overlap
        available = min(available, int(np.count_nonzero(textured & base)))
        one_mean = one_mean._replace(available=available)
    # Blocks are judged by their residual from a smooth trend over the
    # block rows, which are scanned at different times (._trend).
    need = needed_blocks(config, available)
    trend_valid = np.empty_like(measured)
    n_trend, tx, ty, significant = select_by_trend(
        vectors_px, row_px, usable, rule=mad, out=trend_valid
    )
    one_mean_ok = n_valid >= need and max(spread_x, spread_y) <= config.max_block_spread_px
    if not (n_trend >= need and (significant or not one_mean_ok)):
        return one_mean
    # The drift changed while the frame was scanned: the trend over the
    # rows explains the blocks better than one mean does.
    _selection.masked_mean_std(vectors_px, trend_valid, 1, stats)
    return Selection(trend_valid, n_trend, available, (float(stats[0]), float(stats[1])), (tx, ty))

"""A non-rigid frame is not disagreement: the blocks' field over the frame.

A frame whose blocks disagree about one shift, even about a smooth trend
over the rows (the drift changing while the frame was scanned, ``._trend``),
may still be one frame of the same sample, only not rigid: the scanner's
fast axis bows (its x position is not linear in the drive), the lines bow,
the frame turns a little, creep acts along both axes. Whole-image methods
agree on one shift there; the blocks vary smoothly across the frame.

:func:`fit_field` fits the block vectors, per axis, by a smooth field over
the frame (a polynomial of degree :data:`FIELD_DEGREE` in the block's
column and row, robustly: the median/MAD rule on its residuals, refitted on
the blocks kept). The answer stays the trajectory's: the mean of the blocks
kept, at their scan times (a trend over the rows is the drift changing
during the scan, which the trajectory follows). Its σ carries the
distortion:

- the blocks' own scatter about the field, counted by their unshared area;
- what the blocks cannot see: their centres do not reach the frame's edges,
  and across the fast axis the field's mean over the current frame's whole
  width (at the blocks' rows) differs from its mean over the blocks; that
  difference is added as an uncertainty of its own size.

The field is used where the one shift (or trend over the rows) is refused
and the field explains the blocks (their residual spread about it within
``max_block_spread_px``), and where its dependence on the column is
significant (the F rule of the trend over the rows, ``._trend``): there the
one-shift σ would claim a precision the frame does not have (a fast axis
bowed by 1 px put answers 8σ off). The answer is refused where the
distortion makes one shift meaningless: when the field's departure across
the fast axis (RMS over the frame) exceeds :data:`MAX_DISTORTION_FRACTION`
of the block size (4 px for 32 px blocks, 8 px for 64 px blocks). Beyond
that, a block's own window holds content displaced by more than a pixel or
so from edge to edge (its peak smears, and its vector is no longer a point
of the field), and parts of the frame a few blocks apart moved by more than
half a block relative to each other: no single shift places the frame.
Figures: ``benchmarks/distortion_sweep.py`` (``docs/registration.md``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = [
    "FIELD_DEGREE",
    "MAX_DISTORTION_FRACTION",
    "FieldFit",
    "describe",
    "distortion_limit_px",
    "fit_field",
]

F64 = npt.NDArray[np.float64]

#: Degree of the field's polynomial in the block's column and row.
FIELD_DEGREE = 2
#: Largest spread of the field over the frame (RMS, px) as a fraction of the
#: block size: 4 px for 32 px blocks, 8 px for 64 px blocks.
MAX_DISTORTION_FRACTION = 0.125
#: Robust rule on the residuals: threshold (robust z) and floor of the scale (px).
MAD_THRESHOLD = 3.5
MAD_FLOOR_PX = 0.05
#: Blocks the fit needs beyond its coefficients.
SPARE_BLOCKS = 4


class FieldFit(NamedTuple):
    """Result of :func:`fit_field`."""

    valid: npt.NDArray[np.bool_]
    """Blocks kept by the robust rule."""
    mean_px: tuple[float, float]
    """The drift ``(x, y)``, px: the mean of the blocks kept (the
    trajectory's answer, at their scan times)."""
    sigma_px: tuple[float, float]
    """Its uncertainty ``(x, y)``, px, which carries the distortion: the
    blocks' own (their residual spread about the field, counted by their
    unshared area), and what they cannot see of the current frame's width
    (the field's mean over the whole width at their rows less its mean over
    the blocks), at its own size."""
    spread_px: tuple[float, float]
    """Residual standard deviation of the kept blocks about the field."""
    distortion_px: tuple[float, float]
    """RMS over the frame of the field's departure from its mean over the
    width at each row: how far the frame's parts across the fast axis moved
    apart (the non-rigid part; a trend over the rows is the drift changing
    during the scan, not a distortion)."""
    significant: bool
    """The field's dependence on the column explains the blocks better than
    a trend over the rows alone (F statistic above ``f_min``, at least
    ``explained_min`` of the rows-only residual explained)."""


def _terms(u: F64, v: F64, *, columns: bool = True) -> F64:
    cols = [np.ones_like(u)]
    for total in range(1, FIELD_DEGREE + 1):
        for i in range(total + 1):
            if columns or i == total:  # rows only: v, v², ...
                cols.append(u ** (total - i) * v**i)
    return np.stack(cols, axis=1)


def _robust_fit(
    design: F64,
    vectors_px: F64,
    usable: npt.NDArray[np.bool_],
    start: npt.NDArray[np.bool_] | None,
) -> tuple[npt.NDArray[np.bool_], F64] | None:
    """Least squares of ``vectors_px`` on ``design`` over the blocks kept by
    the median/MAD rule on the residuals, refitted until nothing changes;
    the first fit is over ``start`` (default: every usable block)."""
    k = design.shape[1]
    keep = (usable if start is None else start & usable).copy()
    for _ in range(10):
        if int(keep.sum()) < k + SPARE_BLOCKS:
            return None
        coef: F64 = np.asarray(
            np.linalg.lstsq(design[keep], vectors_px[keep], rcond=None)[0], dtype=np.float64
        )
        res = vectors_px - design @ coef
        new = usable.copy()
        for axis in range(2):
            r = res[keep, axis]
            med = float(np.median(r))
            scale = max(1.4826 * float(np.median(np.abs(r - med))), MAD_FLOOR_PX)
            new &= np.abs(res[:, axis] - med) <= MAD_THRESHOLD * scale
        if np.array_equal(new, keep):
            return keep, coef
        keep = new
    return (keep, coef) if int(keep.sum()) >= k + SPARE_BLOCKS else None


#: Columns sampled across the width for the mean over it.
WIDTH_SAMPLES = 257


def fit_field(
    vectors_px: F64,
    centres_px: F64,
    usable: npt.NDArray[np.bool_],
    *,
    frame_shape: tuple[int, int],
    independent: float,
    f_min: float,
    explained_min: float,
    start: npt.NDArray[np.bool_] | None = None,
    force: bool = False,
) -> FieldFit | None:
    """The smooth field over the frame that the ``usable`` block vectors follow.

    Parameters
    ----------
    vectors_px : ndarray, shape (n, 2)
        Block vectors ``(dx, dy)``, px.
    centres_px : ndarray, shape (n, 2)
        Where each vector applies ``(x, y)``, reference px.
    usable : ndarray of bool, shape (n,)
        Blocks that may be kept.
    frame_shape : (int, int)
        ``(rows, cols)`` of the frame.
    independent : float
        The share of a block that is its own (``BlockLayout.overlap_factor``):
        blocks whose windows overlap count for that much each.
    f_min, explained_min : float
        The significance rule of the trend over the rows (``._trend``),
        applied to the column terms.
    start : ndarray of bool, shape (n,), optional
        The blocks the first fit is over (the blocks a one shift or trend
        kept, when it did: a flat region's blocks, which vote zero, must not
        bend the field); later rounds judge every usable block.

    force : bool
        Answer (mean, σ, distortion) even when the column terms are not
        significant (the one shift or trend was refused); otherwise a field
        that is not significant comes back with NaN in their place.

    Returns
    -------
    FieldFit, or None when too few blocks remain for the fit.
    """
    rows, cols = frame_shape
    cx, cy = (cols - 1) / 2, (rows - 1) / 2
    u = (centres_px[:, 0] - cx) / (cols / 2)
    v = (centres_px[:, 1] - cy) / (rows / 2)
    design = _terms(u, v)
    k = design.shape[1]
    fitted = _robust_fit(design, vectors_px, usable, start)
    if fitted is None:
        return None
    keep, coef = fitted
    n = int(keep.sum())
    res = vectors_px[keep] - design[keep] @ coef
    rss = (res**2).sum(axis=0)
    spread = np.sqrt(rss / (n - k))
    # the rows-only model on the same blocks: do the columns matter?
    rows_only = _terms(u, v, columns=False)
    coef_r, *_ = np.linalg.lstsq(rows_only[keep], vectors_px[keep], rcond=None)
    rss_r = ((vectors_px[keep] - rows_only[keep] @ coef_r) ** 2).sum(axis=0)
    extra = k - rows_only.shape[1]
    gain = float(rss_r.sum() - rss.sum()) / (2 * extra)
    noise = max(float(rss.sum()) / (2 * (n - k)), (MAD_FLOOR_PX / 2) ** 2)
    explained = 1.0 - float(rss.sum()) / max(float(rss_r.sum()), 1e-300)
    significant = gain / noise > f_min and explained >= explained_min
    if not (force or significant):
        # a rigid frame (every frame of most runs): the answer is not needed,
        # and the field's means below cost more than the block pass's own
        # post-processing
        nan = (float("nan"), float("nan"))
        return FieldFit(keep, nan, nan, (float(spread[0]), float(spread[1])), nan, False)
    # The drift at the kept blocks' rows, over the whole width of the
    # current frame (the reference's columns moved by the drift, in the
    # reference's coordinates the field is fitted in): the mean of the
    # design over that width at each block's row, averaged over the blocks.
    over_blocks = design[keep].mean(axis=0) @ coef
    width = np.linspace(-1 + 1 / cols, 1 - 1 / cols, WIDTH_SAMPLES)
    width = width - float(over_blocks[0]) / (cols / 2)
    g = np.zeros(k)
    for vb in v[keep]:
        g += _terms(width, np.full_like(width, vb)).mean(axis=0)
    g /= n
    mean = g @ coef
    # the column-dependent departure over the frame
    gv = np.linspace(-1 + 1 / rows, 1 - 1 / rows, 65)
    uu, vv = np.meshgrid(width, gv)
    grid = _terms(uu.ravel(), vv.ravel()) @ coef
    grid = grid.reshape(len(gv), len(width), 2)
    departure = grid - grid.mean(axis=1, keepdims=True)
    distortion = np.sqrt((departure**2).mean(axis=(0, 1)))
    # The answer is the kept blocks' mean (the trajectory's answer, at their
    # scan times); what the blocks cannot see of the frame's width (the
    # field's mean over it less its mean over the blocks) is added to its
    # uncertainty, at its own size.
    block_mean = vectors_px[keep].mean(axis=0)
    var_mean = spread**2 / max(1.0, n * independent)
    extrapolation = mean - over_blocks
    sigma = np.sqrt(var_mean + extrapolation**2)
    mean = block_mean
    return FieldFit(
        keep,
        (float(mean[0]), float(mean[1])),
        (float(sigma[0]), float(sigma[1])),
        (float(spread[0]), float(spread[1])),
        (float(distortion[0]), float(distortion[1])),
        bool(significant),
    )


def distortion_limit_px(block_size: int) -> float:
    """Largest field spread over the frame (RMS, px) at which one shift still
    places the frame (see the module docstring)."""
    return MAX_DISTORTION_FRACTION * block_size


def describe(fit: FieldFit) -> str:
    """One line for the result's reason or note."""
    return (
        f"a non-rigid frame: the blocks follow a smooth field over the frame (spread "
        f"({fit.distortion_px[0]:.2f}, {fit.distortion_px[1]:.2f}) px RMS, residual "
        f"({fit.spread_px[0]:.2f}, {fit.spread_px[1]:.2f}) px)"
    )

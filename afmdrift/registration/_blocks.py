"""Gradient image (eq. 2), block grid and raised-cosine window (eq. 4).

Border handling
---------------
Every extended window lies entirely inside the gradient image: no padding is
ever invented. Along an axis of length ``G`` (gradient image), with extended
size ``E``, block size ``B`` and search radius ``s``, the grid has
``n = ceil(G / B)`` windows whose top-left corners are spread evenly (rounded
to whole pixels) from ``m`` to ``G - E - m``, with a margin
``m = min(s // 2, (G - E) // 4)`` that lets the windows of the current frame
follow a drift of up to ``m`` pixels without leaving the image. A 512-px axis
gets 8 windows of 128 px, 50 px apart; for sizes that are not a multiple of
the block (512×256, 200×200) the windows just overlap more. When
``G < E + B`` (too short for two windows a block apart, e.g. 100 or 64 px),
the windows shrink to about two thirds of the axis (even) and the block to
half of that, so that several windows and some search range remain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.registration import _spectra

__all__ = [
    "BlockLayout",
    "FrameStats",
    "compiled_gradient",
    "gradient_and_stats",
    "gradient_image",
    "gradient_shape",
    "raised_cosine",
]

Gradient = Literal["x", "y", "both", "none", "levelled"]

#: ``gradient = "auto"``: the x gradient is kept unless its signal is below this
#: fraction of its noise (then the levelled heights carry the texture). Measured
#: gradient SNRs: 0.12–0.24 for particles, rough and terrace textures at height
#: SNR 5 (kept: with levelled heights their σ covered only 75–87 % of the errors
#: within 2σ), 0.03 at SNR 2 and ≤ 0.03 at SNR 1 (levelled).
AUTO_GRADIENT_SNR = 0.08


def gradient_shape(shape: tuple[int, int], gradient: Gradient) -> tuple[int, int]:
    """Shape ``(rows, cols)`` of :func:`gradient_image` for an image of ``shape``."""
    rows, cols = shape
    return (rows - (gradient in ("y", "both")), cols - (gradient in ("x", "both")))


def gradient_offset_px(gradient: Gradient) -> tuple[float, float]:
    """Position ``(x, y)`` in image pixels of gradient pixel ``[0, 0]``."""
    return (0.5 if gradient in ("x", "both") else 0.0, 0.5 if gradient in ("y", "both") else 0.0)


def gradient_image(
    heights: npt.NDArray[np.floating],
    gradient: Gradient,
    *,
    out: npt.NDArray[np.float32] | None = None,
) -> npt.NDArray[np.float32]:
    """Gradient image of eq. (2) of Yang et al. (2008), in float32.

    ``"x"``: ``g = h(x, y) - h(x - 1, y)`` along the fast axis (per-line
    offsets cancel; a tilt becomes a constant that block mean removal
    cancels). ``"y"``: the same along rows. ``"both"``: the magnitude
    ``hypot(gx, gy)`` (rotation-symmetric edges, but no longer invariant to
    line offsets or tilt). ``"none"``: the heights themselves.

    Parameters
    ----------
    heights : ndarray, shape (rows, cols)
    gradient : {"x", "y", "both", "none"}
    out : ndarray, float32, optional
        Array to write into (shape :func:`gradient_shape`); default: a new one.

    Returns
    -------
    ndarray, shape :func:`gradient_shape`, float32
    """
    h = heights
    rows, cols = gradient_shape((int(h.shape[0]), int(h.shape[1])), gradient)
    if out is None:
        out = np.empty((rows, cols), dtype=np.float32)
    # Differences are taken in the input precision and only then rounded to
    # float32, so a large z offset does not eat the texture's digits.
    if compiled_gradient(h, gradient):
        _spectra.gradient_x(h, out)  # one compiled pass (its figures unused here)
    elif gradient == "x":
        np.subtract(h[:, 1:], h[:, :-1], out=out, casting="same_kind")
    elif gradient == "y":
        np.subtract(h[1:, :], h[:-1, :], out=out, casting="same_kind")
    elif gradient == "both":
        gx = np.subtract(h[:-1, 1:], h[:-1, :-1])
        gy = np.subtract(h[1:, :-1], h[:-1, :-1])
        np.hypot(gx, gy, out=out, casting="same_kind")
    elif gradient == "levelled":
        out[...] = levelled(h)
    else:
        out[...] = h
    return out


def levelled(heights: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
    """Heights with a least-squares line removed from every scan line (first
    order line levelling): per-line offsets and the tilt along the fast axis
    cancel, as in the x gradient, without differentiating the noise."""
    h = np.asarray(heights, dtype=np.float64)
    x = np.arange(h.shape[1], dtype=np.float64)
    x -= x.mean()
    slope = (h @ x) / float(x @ x)
    out: npt.NDArray[np.float64] = h - h.mean(axis=1, keepdims=True) - slope[:, None] * x
    return out


def config_for_image(
    config: RegistrationConfig, heights: npt.NDArray[np.floating]
) -> RegistrationConfig:
    """The configuration an image is measured with: the block sizes for its
    shape (:meth:`RegistrationConfig.for_shape`) and ``gradient = "auto"``
    resolved from its data (:func:`choose_prefilter`). A pair or a stream is
    measured with the configuration of its reference."""
    cfg = config.for_shape((int(heights.shape[0]), int(heights.shape[1])))
    if cfg.gradient != "auto":
        return cfg
    return cfg.model_copy(update={"gradient": choose_prefilter(heights)})


def choose_prefilter(heights: npt.NDArray[np.floating]) -> Gradient:
    """The pre-filter for ``gradient = "auto"``: the paper's x gradient, or the
    levelled heights where the gradient would bury the signal in noise.

    White noise of standard deviation σ gives the x gradient a variance 2σ²
    and the second difference along x 6σ²; a smooth texture adds little to
    the second difference, so σ ≈ 1.4826 · MAD(second difference) / √6
    (a robust estimate, as in Immerkær, CVIU 64(2), 1996, along one axis).
    The gradient's own signal-to-noise ratio is ``(var(g) − 2σ²) / 2σ²``;
    below :data:`AUTO_GRADIENT_SNR` (smooth textures at HS-AFM scale, where
    neighbouring pixels differ mostly by noise) the levelled heights are used.
    Noise-free frames (σ = 0) keep the x gradient.
    """
    h = np.asarray(heights, dtype=np.float64)
    d2 = h[:, 2:] - 2.0 * h[:, 1:-1] + h[:, :-2]
    sigma2 = (1.4826 * float(np.median(np.abs(d2 - np.median(d2))))) ** 2 / 6.0
    if sigma2 <= 0.0:
        return "x"
    g = np.diff(h, axis=1)
    snr = (float(g.var()) - 2.0 * sigma2) / (2.0 * sigma2)
    return "levelled" if snr < AUTO_GRADIENT_SNR else "x"


class FrameStats(NamedTuple):
    """What the frame checks need of a gradient image (see
    :func:`afmdrift.registration._checks.check_frame`).

    Attributes
    ----------
    finite : bool
        No NaN or infinite pixel in the heights nor in the gradient image.
    nonzero : int
        Non-zero pixels of the gradient image.
    uniform : bool
        All pixels of the gradient image are equal (a constant frame, a plane
        in the x gradient, ...).
    """

    finite: bool
    nonzero: int
    uniform: bool


def compiled_gradient(heights: npt.NDArray[np.floating], gradient: Gradient) -> bool:
    """Whether the gradient image of ``heights`` is the compiled x-gradient
    pass (:func:`afmdrift.registration._spectra.gradient_x`): the x gradient
    of a float32 or float64 image."""
    return gradient == "x" and heights.dtype in (np.float32, np.float64)


def gradient_and_stats(
    heights: npt.NDArray[np.floating],
    gradient: Gradient,
    *,
    out: npt.NDArray[np.float32] | None = None,
) -> tuple[npt.NDArray[np.float32], FrameStats]:
    """:func:`gradient_image` and its :class:`FrameStats`; in one compiled pass
    for the x gradient of a float32 or float64 image (where every pixel
    enters a difference, so a NaN pixel always shows in the gradient)."""
    if compiled_gradient(heights, gradient):
        rows, cols = gradient_shape((int(heights.shape[0]), int(heights.shape[1])), gradient)
        grad = out if out is not None else np.empty((rows, cols), dtype=np.float32)
        finite, nonzero, uniform = _spectra.gradient_x(heights, grad)
        return grad, FrameStats(bool(finite), int(nonzero), bool(uniform))
    grad = gradient_image(heights, gradient, out=out)
    finite = bool(np.isfinite(heights).all() and np.isfinite(grad).all())
    uniform = bool((grad == grad.flat[0]).all())
    return grad, FrameStats(finite, int(np.count_nonzero(grad)), uniform)


def raised_cosine(rows: int, cols: int) -> npt.NDArray[np.float32]:
    """2-D raised-cosine window of eq. (4), shape (rows, cols), float32.

    ``w(x, y) = 1/4 [1 - cos(2π(x + ½)/M)] [1 - cos(2π(y + ½)/N)]``. The
    window is periodic in ``x`` with period ``M``, so its DFT is non-zero
    only at the frequencies 0 and ±1 along each axis.
    """
    return np.outer(raised_cosine_axis(rows), raised_cosine_axis(cols)).astype(np.float32)


def raised_cosine_axis(n: int) -> npt.NDArray[np.float64]:
    """One factor of :func:`raised_cosine`: ``½ [1 - cos(2π(k + ½)/n)]``,
    ``k = 0..n-1``."""
    return 0.5 * (1.0 - np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n))


def _axis(
    length: int, extended: int, block: int, max_shift: float | None
) -> tuple[int, int, int, npt.NDArray[np.intp]]:
    """Extended size, block size, search radius and window starts on one axis."""
    ext = extended
    blk = block
    if length < extended + block:
        # Too short for two windows a block apart: shrink the windows to about
        # two thirds of the axis (even) so that several still fit.
        ext = min(extended, 2 * (length // 3))
        blk = min(block, ext // 2)
    limit = ext // 2 - 2  # keep room for the sub-pixel neighbourhood
    want = (ext - blk) / 2 if max_shift is None else max_shift
    shift = int(max(1, min(limit, math.floor(want))))
    # Leave a margin of half the search radius (at most a quarter of the free
    # range) so windows can follow a drift of that size without clamping.
    margin = min(shift // 2, (length - ext) // 4)
    span = length - ext - 2 * margin
    n = max(1, min(math.ceil(length / blk), span + 1))
    if n == 1:
        starts = np.array([(length - ext) // 2], dtype=np.intp)
    else:
        starts = np.rint(np.linspace(margin, margin + span, n)).astype(np.intp)
    return ext, blk, shift, starts


@dataclass(frozen=True)
class BlockLayout:
    """Where the extended windows lie in the gradient image.

    Attributes
    ----------
    grad_shape : (int, int)
        Gradient image ``(rows, cols)``.
    ext : (int, int)
        Extended window ``(rows, cols)``.
    block : (int, int)
        Inner block ``(rows, cols)``.
    top : ndarray, shape (n,)
        Row of each window's top-left corner.
    left : ndarray, shape (n,)
        Column of each window's top-left corner.
    max_shift : (int, int)
        Largest integer shift searched, ``(rows, cols)``.
    pitch : (float, float)
        Mean spacing of window corners ``(rows, cols)`` (block size if one).
    """

    grad_shape: tuple[int, int]
    ext: tuple[int, int]
    block: tuple[int, int]
    top: npt.NDArray[np.intp]
    left: npt.NDArray[np.intp]
    max_shift: tuple[int, int]
    pitch: tuple[float, float]

    @classmethod
    def build(
        cls,
        grad_shape: tuple[int, int],
        *,
        extended_size: int,
        block_size: int,
        block_search_px: float | None,
    ) -> BlockLayout:
        rows, cols = grad_shape
        ey, by, sy, ys = _axis(rows, extended_size, block_size, block_search_px)
        ex, bx, sx, xs = _axis(cols, extended_size, block_size, block_search_px)
        shifts = (sy, sx)
        top, left = np.meshgrid(ys, xs, indexing="ij")
        pitch_y = float(np.mean(np.diff(ys))) if ys.size > 1 else float(by)
        pitch_x = float(np.mean(np.diff(xs))) if xs.size > 1 else float(bx)
        return cls(
            grad_shape=(rows, cols),
            ext=(ey, ex),
            block=(by, bx),
            top=top.ravel(),
            left=left.ravel(),
            max_shift=(shifts[0], shifts[1]),
            pitch=(pitch_y, pitch_x),
        )

    @property
    def n_blocks(self) -> int:
        return int(self.top.size)

    def overlap_factor(self) -> float:
        """Fraction of each inner block not shared with its neighbours (≤ 1)."""
        return min(1.0, self.pitch[0] / self.block[0]) * min(1.0, self.pitch[1] / self.block[1])

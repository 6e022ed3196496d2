"""De-warped frames: each row moved back by the drift at its scan time.

A frame scanned while the sample drifts is distorted row by row: the content
of row r was displaced by the image position m(t_r) (drift, scan-direction
bias and commanded offset moves; ``afmdrift.model._positions``) at the row's
scan time t_r. Gwyddion's "Compensate Drift" corrects one frame along the
fast axis; here the drift trajectory gives m(t) on both axes and across
frames, so every corrected frame is in the geometry of the session reference
(p = 0).

For output row y (reference geometry) the input row y_in is the solution of
``y_in − m_y(t(y_in))/Δy = y`` (two fixed-point steps: m changes by far less
than a pixel per row), and the row is read at x + m_x(t(y_in))/Δx, with cubic
spline interpolation (``scipy.ndimage.map_coordinates``). Content that was not
scanned in the frame is ``fill``: NaN, or the nearest scanned value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from afmdrift.model import FrameTrajectory, offset_change_nm
from afmdrift.records import Event, Frame

__all__ = ["dewarp_frame", "image_positions", "interp_linear"]

FloatArray = npt.NDArray[np.float64]


def interp_linear(t: FloatArray, knots_t: FloatArray, knots_v: FloatArray) -> FloatArray:
    """Linear interpolation of ``knots_v`` (k,) at ``t``, extended linearly
    beyond the first and last knot (not clamped)."""
    if knots_t.size == 1:
        return np.full(t.shape, float(knots_v[0]))
    out = np.interp(t, knots_t, knots_v)
    lo = t < knots_t[0]
    hi = t > knots_t[-1]
    s0 = (knots_v[1] - knots_v[0]) / (knots_t[1] - knots_t[0])
    s1 = (knots_v[-1] - knots_v[-2]) / (knots_t[-1] - knots_t[-2])
    out[lo] = knots_v[0] + s0 * (t[lo] - knots_t[0])
    out[hi] = knots_v[-1] + s1 * (t[hi] - knots_t[-1])
    return np.asarray(out, dtype=np.float64)


def dewarp_frame(
    frame: Frame,
    t_s: npt.ArrayLike,
    image_position_nm: npt.ArrayLike,
    *,
    fill: Literal["nan", "nearest"] = "nan",
) -> npt.NDArray[np.float32]:
    """The frame in the reference geometry, shape (rows, cols), float32, nm.

    Parameters
    ----------
    frame : Frame
        The frame (its timing gives each row's scan time).
    t_s : array_like, shape (k,)
        Times of the image position samples, increasing, s.
    image_position_nm : array_like, shape (k, 2)
        Image position m (x, y) at ``t_s``, nm: the drift trajectory with the
        commanded offset change removed, m = p − (O(t) − O(t_ref)).
    fill : {"nan", "nearest"}
        Value where the output needs content the frame did not scan.

    Raises
    ------
    ValueError
        No samples, non-finite samples, or shapes that disagree.
    """
    tk = np.asarray(t_s, dtype=np.float64).reshape(-1)
    mk = np.asarray(image_position_nm, dtype=np.float64).reshape(-1, 2)
    if tk.size == 0 or mk.shape[0] != tk.size:
        raise ValueError(f"need one (x, y) image position per time, got {tk.size} and {mk.shape}")
    if not (np.all(np.isfinite(tk)) and np.all(np.isfinite(mk))):
        raise ValueError("image position samples must be finite")
    order = np.argsort(tk)
    tk, mk = tk[order], mk[order]
    rows, cols = frame.shape
    px, py = frame.pixel_size_nm
    row_t = frame.row_times_s()
    idx = np.arange(rows, dtype=np.float64)

    def shift_px(y_in: FloatArray) -> tuple[FloatArray, FloatArray]:
        t = np.interp(y_in, idx, row_t, left=np.nan, right=np.nan)
        # rows outside the frame: extend the row-time line
        slope = (row_t[-1] - row_t[0]) / max(rows - 1, 1)
        bad = ~np.isfinite(t)
        t[bad] = row_t[0] + slope * y_in[bad]
        return interp_linear(t, tk, mk[:, 0]) / px, interp_linear(t, tk, mk[:, 1]) / py

    y_out = idx
    y_in = y_out.copy()
    for _ in range(3):
        _, sy = shift_px(y_in)
        y_in = y_out + sy
    sx, _ = shift_px(y_in)
    yy = np.repeat(y_in[:, None], cols, axis=1)
    xx = np.arange(cols, dtype=np.float64)[None, :] + sx[:, None]
    heights = np.asarray(frame.heights_nm, dtype=np.float64)
    out = ndimage.map_coordinates(heights, [yy, xx], order=3, mode="nearest")
    if fill == "nan":
        outside = (yy < -0.5) | (yy > rows - 0.5) | (xx < -0.5) | (xx > cols - 0.5)
        out[outside] = np.nan
    return np.asarray(out, dtype=np.float32)


def image_positions(
    trajectory: FrameTrajectory, events: Sequence[Event], t_ref_s: float
) -> FloatArray:
    """Image position m at a frame's trajectory samples, shape (k, 2), nm:
    the drift with the commanded offset change since the reference removed,
    m = p − (O(t) − O(t_ref))."""
    offset = offset_change_nm(trajectory.t_s, t_ref_s, events)
    return np.asarray(trajectory.xy_nm - offset, dtype=np.float64)

"""Whole-frame coarse alignment: the integer prior of :func:`measure_drift`.

When no expected drift is known, the two gradient images are binned 2×2,
windowed with the raised cosine of eq. (4) over the whole frame and phase
correlated once. The integer peak (times two) moves the block windows close
to their content, so the block stage only has to resolve a small residual:
that both widens the measurable range beyond the block search radius and
keeps the window-induced bias of large in-window shifts away.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from afmdrift.registration._blocks import raised_cosine

__all__ = ["coarse_shift"]


def _bin2(img: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    rows, cols = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    out: npt.NDArray[np.float32] = (
        img[:rows, :cols].reshape(rows // 2, 2, cols // 2, 2).mean(axis=(1, 3), dtype=np.float32)
    )
    return out


def coarse_shift(
    g_ref: npt.NDArray[np.float32], g_cur: npt.NDArray[np.float32], *, eps_rel: float
) -> tuple[int, int]:
    """Integer drift ``(dx, dy)`` in px of ``g_cur`` relative to ``g_ref``.

    Parameters
    ----------
    g_ref, g_cur : ndarray, shape (rows, cols), float32
        Gradient images of equal shape.
    eps_rel : float
        Magnitude floor of the normalised cross-power, relative to its maximum.
    """
    a = _bin2(g_ref)
    b = _bin2(g_cur)
    win = raised_cosine(*a.shape)
    fa = np.fft.rfft2((a - np.average(a, weights=win)) * win)
    fb = np.fft.rfft2((b - np.average(b, weights=win)) * win)
    cross = fb * np.conj(fa)
    mag = np.abs(cross)
    cross /= mag + eps_rel * float(mag.max()) + np.finfo(np.float64).tiny
    corr = np.fft.irfft2(cross, s=a.shape)
    iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
    rows, cols = a.shape
    sy = iy - rows if iy > rows // 2 else iy
    sx = ix - cols if ix > cols // 2 else ix
    return 2 * int(sx), 2 * int(sy)

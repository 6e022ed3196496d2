"""Whole-frame coarse alignment: the integer prior of :func:`measure_drift`.

When no expected drift is known, one phase correlation of the two whole
height images gives the integer shift; the block windows are then moved by
it, so the block stage only has to resolve a small residual. That both
widens the measurable range beyond the block search radius and keeps the
window-induced bias of large in-window shifts away.

The shift is the highest peak of the phase correlation of the two images
with their per-line medians removed (line levelling, which takes out the
line-to-line offsets of AFM scans), without a window. It is used only when
two checks agree (:attr:`CoarseShift.trusted`): the peak stands out of its
correlation surface, and the x-gradient images (eq. 2 of Yang et al. 2008,
what the block engine sees) also correlate at that shift. On the real
NanoScope pair (a lattice with a period of about 10 px, true shift about
(0, 28) px) this gives (0, 28); the previous method (2×2-binned gradient
images under a raised-cosine window) gave (2, 18), a wrong lattice peak, and
a Hann window on the heights moved the peak to 18 px as well.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = ["COARSE_MIN_GRADIENT_Z", "COARSE_MIN_Z", "CoarseShift", "coarse_shift"]

#: Smallest coarse correlation peak (in standard deviations of the surface) that is used.
COARSE_MIN_Z = 6.0
#: Smallest x-gradient correlation at the coarse shift (one location, so 3 sigma suffices).
COARSE_MIN_GRADIENT_Z = 3.0

F64 = npt.NDArray[np.float64]


class CoarseShift(NamedTuple):
    """Result of :func:`coarse_shift`."""

    dx_px: float
    dy_px: float
    peak_z: float
    """Peak of the line-levelled correlation over its surface's standard deviation."""
    gradient_z: float
    """The x-gradient correlation at the same shift, in its surface's standard deviations."""

    @property
    def trusted(self) -> bool:
        """Both correlations agree that the shift is real (see :func:`coarse_shift`)."""
        return self.peak_z >= COARSE_MIN_Z and self.gradient_z >= COARSE_MIN_GRADIENT_Z

    @property
    def prior_px(self) -> tuple[float, float]:
        """``(dx, dy)`` when trusted, else ``(0, 0)``."""
        return (self.dx_px, self.dy_px) if self.trusted else (0.0, 0.0)


def _phase_correlation(reference: F64, current: F64) -> F64:
    """Inverse FFT of ``F(cur)·conj(F(ref)) / |…|``: a peak at ``d`` for
    ``cur(u) = ref(u − d)``. The magnitude is floored at 1e-12 of its maximum
    (and at the smallest normal double), so the division is always finite."""
    cross = np.fft.rfft2(current) * np.conj(np.fft.rfft2(reference))
    mag = np.abs(cross)
    np.maximum(mag, float(mag.max()) * 1e-12 + np.finfo(np.float64).tiny, out=mag)
    cross /= mag
    corr: F64 = np.fft.irfft2(cross, s=reference.shape)
    return corr


def _z(corr: F64, r: int, c: int) -> float:
    spread = float(corr.std())
    return float(corr[r, c]) / spread if spread > 0 else 0.0


def coarse_shift(
    reference: npt.NDArray[np.floating], current: npt.NDArray[np.floating]
) -> CoarseShift:
    """Integer drift ``(dx, dy)`` in px from whole-image phase correlations.

    Two significances, each in standard deviations of its correlation
    surface: ``peak_z`` of the levelled-height peak (unrelated images give
    about ``sqrt(2 ln N)``, 4.1 for 200×200 px; consecutive HS-AFM frames
    7–12; the NanoScope pair 19) and ``gradient_z``, the correlation of the
    two x-gradient images at the same shift. Scan-line artefacts (streaks)
    correlate strongly in the levelled heights at spurious shifts (z 14–37
    on HS-AFM frames 22–31 of ``hsafm_sample_0.asd``) but not in the
    x-gradient (z about 0 there, 5–10 on good frames), so
    :attr:`CoarseShift.trusted` requires both. Shifts beyond half the image
    wrap around, so the result only centres the block search.

    Parameters
    ----------
    reference, current : ndarray, shape (rows, cols)
        Height images of equal shape (finite; at least 2 columns).

    Returns
    -------
    CoarseShift
        Integer-valued ``dx_px`` in ``(-cols/2, cols/2]``, ``dy_px`` in
        ``(-rows/2, rows/2]``, ``peak_z`` and ``gradient_z``.
    """

    def levelled(h: npt.NDArray[np.floating]) -> F64:
        g = np.asarray(h, dtype=np.float64)
        out: F64 = g - np.median(g, axis=1, keepdims=True)
        return out

    def gradient(h: npt.NDArray[np.floating]) -> F64:
        g: F64 = np.diff(np.asarray(h, dtype=np.float64), axis=1)
        g -= float(g.mean())
        return g

    corr = _phase_correlation(levelled(reference), levelled(current))
    rows, cols = corr.shape
    r, c = (int(v) for v in np.unravel_index(int(np.argmax(corr)), corr.shape))
    dy = r - rows if r > rows // 2 else r
    dx = c - cols if c > cols // 2 else c
    g_corr = _phase_correlation(gradient(reference), gradient(current))
    g_z = _z(g_corr, dy % g_corr.shape[0], dx % g_corr.shape[1])
    return CoarseShift(float(dx), float(dy), _z(corr, r, c), g_z)

"""Rejection of blocks whose motion disagrees with the frame's drift.

Two rules (``RegistrationConfig.outlier_rule``):

``"paper"``
    Yang et al. (2008): compute the mean vector of the measured blocks and
    drop every block farther than ``epsilon_px`` (Euclidean) from it; one pass.
    Simple, but the mean itself is pulled by the outliers, so with many
    altered blocks good blocks can be dropped and bad ones kept.
``"mad"`` (default)
    Iterated median/MAD: per axis, robust z = |v − median| / (1.4826·MAD),
    with the MAD floored at ``MAD_FLOOR_PX`` so that near-identical vectors
    are not split by rounding noise; drop blocks with z > ``mad_threshold``
    on either axis and repeat on the survivors until nothing changes.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from afmdrift.registration import _kernels

__all__ = ["MAD_FLOOR_PX", "MAX_ITER", "reject_mad", "reject_paper"]

#: Smallest robust scale (px): sub-pixel estimator noise well below this is
#: not evidence of a different motion.
MAD_FLOOR_PX = 0.05
#: Most rounds of the MAD rule.
MAX_ITER = 20


def reject_paper(
    vectors_px: npt.NDArray[np.float64], keep: npt.NDArray[np.bool_], *, epsilon_px: float
) -> npt.NDArray[np.bool_]:
    """Paper's rule: keep blocks within ``epsilon_px`` of the mean vector
    (compiled: :func:`afmdrift.registration._kernels.reject_paper`).

    Parameters
    ----------
    vectors_px : ndarray, shape (n, 2)
    keep : ndarray of bool, shape (n,)
        Blocks taking part (others stay rejected).
    epsilon_px : float

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    out = np.empty_like(keep)
    _kernels.reject_paper(np.ascontiguousarray(vectors_px, dtype=np.float64), keep, epsilon_px, out)
    return out


def reject_mad(
    vectors_px: npt.NDArray[np.float64], keep: npt.NDArray[np.bool_], *, threshold: float
) -> npt.NDArray[np.bool_]:
    """Iterated per-axis median/MAD rule; see the module docstring (compiled:
    :func:`afmdrift.registration._kernels.reject_mad`)."""
    out = np.empty_like(keep)
    _kernels.reject_mad(
        np.ascontiguousarray(vectors_px, dtype=np.float64), keep, threshold, MAD_FLOOR_PX,
        MAX_ITER, out,
    )  # fmt: skip
    return out

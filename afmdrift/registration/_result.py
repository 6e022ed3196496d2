"""Result records of the registration engine."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["BlockField", "DriftResult"]


@dataclass(frozen=True, eq=False)
class BlockField:
    """Per-block motion field of one registration.

    Attributes
    ----------
    centres_px : ndarray, shape (n, 2)
        Block centres ``(x, y)`` in reference image pixels.
    vectors_px : ndarray, shape (n, 2)
        Motion ``(dx, dy)`` of each block in pixels (same sign convention as
        the frame drift). Meaningless where ``measured`` is False.
    confidence : ndarray, shape (n,)
        Height of the normalised phase-correlation peak (1 for a perfect
        match, about ``1/sqrt(N)`` for noise).
    mse : ndarray, shape (n,)
        Mean squared difference of the gradient blocks at the chosen integer
        shift (gradient units², NaN if no candidate could be checked).
    measured : ndarray of bool, shape (n,)
        A usable peak was found inside the search range and overlap.
    valid : ndarray of bool, shape (n,)
        Measured and kept by the outlier rule: these blocks make the drift.
    weight_centres_px : ndarray, shape (n, 2)
        Where each block's vector applies ``(x, y)``, reference image pixels:
        the centre of its correlation weight (the window squared times the
        reference block's gradient energy), not the window's centre. When the
        drift moves while the frame is scanned, a block measures the shift of
        the rows its texture is in: a particle near the top of a window is
        scanned up to 16 s before the window's centre row in a 512-line,
        4 Hz frame.
    """

    centres_px: npt.NDArray[np.floating]
    vectors_px: npt.NDArray[np.floating]
    confidence: npt.NDArray[np.floating]
    mse: npt.NDArray[np.floating]
    measured: npt.NDArray[np.bool_]
    valid: npt.NDArray[np.bool_]
    weight_centres_px: npt.NDArray[np.floating]

    def valid_mean_std_px(self, *, ddof: int) -> tuple[int, npt.NDArray[np.float64]]:
        """The number of valid blocks, and their mean vector ``[0:2]`` and
        standard deviation ``[2:4]`` (``(x, y)``, px; ``ddof`` as NumPy's
        ``std``, NaN where undefined): the kernel the frame's drift is
        combined with."""
        from afmdrift.registration import _selection

        valid = np.ascontiguousarray(self.valid, dtype=bool).reshape(-1)
        vectors = np.ascontiguousarray(self.vectors_px, dtype=np.float64).reshape(-1, 2)
        out = np.empty(4)
        _selection.masked_mean_std(vectors, valid, ddof, out)
        return int(np.count_nonzero(valid)), out

    def valid_row_means_px(
        self,
    ) -> tuple[int, npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64],
               npt.NDArray[np.float64]]:  # fmt: skip
        """The valid blocks grouped by grid row (the rows the trend rule fits
        over): their number, and per row (sorted) the row, its number of
        blocks, their mean vector ``(x, y)`` and the mean row of their
        weight centres (where the row's vector applies), all px."""
        from afmdrift.registration import _selection

        valid = np.ascontiguousarray(self.valid, dtype=bool).reshape(-1)
        n = valid.size
        levels, counts, at = np.empty((3, n))
        means = np.empty((n, 2))
        n_valid, n_rows = _selection.row_means(
            valid,
            np.ascontiguousarray(self.vectors_px, dtype=np.float64).reshape(-1, 2),
            np.ascontiguousarray(self.centres_px[:, 1], dtype=np.float64),
            np.ascontiguousarray(self.weight_centres_px[:, 1], dtype=np.float64),
            _selection.RowMeans(levels, counts, means, at),
        )
        return int(n_valid), levels[:n_rows], counts[:n_rows], means[:n_rows], at[:n_rows]


def _json_float(v: float) -> float | None:
    return v if math.isfinite(v) else None


@dataclass(frozen=True, eq=False)
class DriftResult:
    """Drift between two frames.

    Sign convention: a feature at ``u`` in the reference appears at
    ``u + d`` in the current frame; x is along columns, y along rows.

    Attributes
    ----------
    dx_px, dy_px : float
        Mean motion of the valid blocks, px (NaN when ``valid`` is False).
    dx_nm, dy_nm : float
        The same in nm (x and y pixel sizes applied separately).
    sigma_x_nm, sigma_y_nm : float
        Standard uncertainty of the mean from the spread of the valid blocks
        (see docs/registration.md for the effective block count).
    sigma_nm : float
        RMS of the two axes' uncertainties.
    valid : bool
        At least ``min_valid_blocks`` blocks survived.
    valid_blocks, total_blocks : int
    reason : str or None
        Why the result is invalid.
    field : BlockField
        Per-block detail.
    prior_px : (float, float) or None
        Where the block search was centred (the expected drift), px.
    prior : str
        Where that came from: ``given``, ``predicted``, ``none``, or the
        coarse alignment with its scores (:meth:`CoarseShift.describe`).
    lattice_px : tuple of (float, float)
        A valid result: other shifts the images cannot tell apart (lattice
        translations of a periodic sample), as offsets from the result; the
        one nearest the prior was taken. A result refused as ambiguous: the
        tied shifts themselves (px), nearest zero (or the prior) first.
    expected_px : (float, float) or None
        The expected drift as it was given (``prior`` starts with ``given``)
        or predicted (``predicted``), px, before any coarse alignment moved
        the search; None when nothing was expected.
    decided_by : str or None
        What picked the shift among those the images allow: ``content`` (the
        frames' content: no other shift fits as well), ``bound`` (lattice
        translations fit alike and only this one lies within the stated
        ``max_shift_px``), ``equivalent`` (they fit alike and, as
        ``lattice = "equivalent"`` asks, the one nearest the prior or zero
        was taken: the frames are registered, the drift is not known),
        ``prior`` (they fit alike and the prior alone picked the one nearest
        it; the result is only as good as the prior). None when invalid.
    alternatives_px : tuple of (float, float)
        ``decided_by`` ``prior``, ``equivalent`` or ``bound``: the other
        shifts that fit as well (px; for ``bound`` those beyond it), nearest
        the prior (or zero) first.
    ambiguity_px : float
        Same cases: distance from the result to the nearest alternative, px
        (a prior off by half of it would have picked another); NaN
        otherwise.
    distortion_px : (float, float) or None
        A non-rigid frame (:mod:`afmdrift.registration._distortion`): the
        RMS departure ``(x, y)`` of the blocks' smooth field from its mean
        over the frame, px. The result is then the field's mean over the
        frame, and σ carries what the blocks cannot tell of it. None for a
        rigid frame (one shift, or a trend over the rows).
    """

    dx_px: float
    dy_px: float
    dx_nm: float
    dy_nm: float
    sigma_x_nm: float
    sigma_y_nm: float
    sigma_nm: float
    valid: bool
    valid_blocks: int
    total_blocks: int
    reason: str | None
    field: BlockField
    prior_px: tuple[float, float] | None = None
    prior: str = ""
    lattice_px: tuple[tuple[float, float], ...] = ()
    expected_px: tuple[float, float] | None = None
    decided_by: str | None = None
    alternatives_px: tuple[tuple[float, float], ...] = ()
    ambiguity_px: float = math.nan
    distortion_px: tuple[float, float] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (non-finite numbers become None)."""
        return {
            "dx_px": _json_float(self.dx_px),
            "dy_px": _json_float(self.dy_px),
            "dx_nm": _json_float(self.dx_nm),
            "dy_nm": _json_float(self.dy_nm),
            "sigma_x_nm": _json_float(self.sigma_x_nm),
            "sigma_y_nm": _json_float(self.sigma_y_nm),
            "sigma_nm": _json_float(self.sigma_nm),
            "valid": self.valid,
            "valid_blocks": self.valid_blocks,
            "total_blocks": self.total_blocks,
            "reason": self.reason,
            "prior_px": None if self.prior_px is None else list(self.prior_px),
            "prior": self.prior,
            "lattice_px": [list(v) for v in self.lattice_px],
            "expected_px": None if self.expected_px is None else list(self.expected_px),
            "decided_by": self.decided_by,
            "ambiguity_px": _json_float(self.ambiguity_px),
            "distortion_px": None if self.distortion_px is None else list(self.distortion_px),
            "alternatives": [
                {
                    "shift_px": [a, b],
                    "from_prior_px": None
                    if self.expected_px is None
                    else math.hypot(a - self.expected_px[0], b - self.expected_px[1]),
                }
                for a, b in self.alternatives_px
            ],
        }

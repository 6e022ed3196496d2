"""Input checks of the registration: pixel sizes, images, frames (from
their gradient image) and priors."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from afmdrift.registration._blocks import FrameStats
from afmdrift.registration._coarse import coarse_shift
from afmdrift.registration._errors import (
    InvalidFrameError,
    NearlyBlankError,
    RegistrationError,
)

__all__ = [
    "BLANK_LOCK_Z",
    "MIN_IMAGE_PX",
    "MIN_TEXTURE_FRACTION",
    "allow_nearly_blank",
    "check_frame",
    "check_image",
    "check_pixel_size",
    "check_prior",
]

#: Smallest accepted image edge (px).
MIN_IMAGE_PX = 64
#: Smallest share of non-zero gradient pixels of a usable frame.
MIN_TEXTURE_FRACTION = 0.02


def check_pixel_size(pixel_size_nm: float | tuple[float, float]) -> tuple[float, float]:
    """Validate a pixel size (scalar or ``(x, y)``) and return ``(px, py)`` in nm."""
    if isinstance(pixel_size_nm, (int, float, np.floating, np.integer)):
        pair = (float(pixel_size_nm), float(pixel_size_nm))
    else:
        try:
            px, py = pixel_size_nm
            pair = (float(px), float(py))
        except (TypeError, ValueError):
            raise RegistrationError(
                f"pixel_size_nm must be a number or an (x, y) pair, got {pixel_size_nm!r}"
            ) from None
    for name, v in zip(("x", "y"), pair, strict=True):
        if not (math.isfinite(v) and v > 0):
            raise RegistrationError(f"pixel_size_nm {name} must be finite and > 0, got {v!r}")
    return pair


def check_image(image: npt.ArrayLike, name: str) -> npt.NDArray[np.floating]:
    """Validate a height image as an array; return it as a floating array (no
    copy if possible). Its pixel values are checked with its gradient image,
    by :func:`check_frame`.

    Raises
    ------
    InvalidFrameError
        Not 2-D, not real numeric, or smaller than 64 px.
    """
    arr = np.asarray(image)
    if arr.dtype.kind not in "fiu":
        raise InvalidFrameError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise InvalidFrameError(f"{name} must be 2-D (rows, cols), got shape {arr.shape}")
    if min(arr.shape) < MIN_IMAGE_PX:
        raise InvalidFrameError(
            f"{name} is too small: shape {arr.shape}, need at least "
            f"{MIN_IMAGE_PX}×{MIN_IMAGE_PX} px"
        )
    if arr.dtype.kind != "f":
        arr = arr.astype(np.float64)
    return arr


def check_frame(
    heights: npt.NDArray[np.floating],
    grad: npt.NDArray[np.float32],
    stats: FrameStats,
    name: str,
    *,
    gradient: str,
) -> None:
    """Refuse a frame with nothing to register, given its gradient image
    ``grad`` and the :class:`FrameStats` found with it
    (:meth:`BlockEngine.prepare`). The heights themselves are only looked at
    again to name what is wrong.

    Raises
    ------
    InvalidFrameError
        NaN/Inf pixels (or height differences beyond float32); a constant
        frame, or a gradient image without texture (a plane); or, for the
        gradient modes (``gradient`` not ``"none"``), fewer than
        :data:`MIN_TEXTURE_FRACTION` of the gradient's pixels non-zero: a
        near-blank frame, e.g. HS-AFM frame 27 of ``hsafm_sample_0.asd``
        (9 height levels, 0.18 % non-zero x-gradient; good frames of that
        movie 70–75 %), on which a few blocks once agreed on a confident
        wrong drift of (−19.5, 11.2) px.
    """
    if not stats.finite or stats.uniform:
        lo, hi = float(heights.min()), float(heights.max())
        _check_values(heights, name, lo, hi)
        if not stats.finite:
            raise InvalidFrameError(
                f"{name} has height differences beyond the float32 range (heights "
                f"{lo:g} .. {hi:g} nm): not a height image in nm?"
            )
        raise InvalidFrameError(
            f"{name} has no texture in its gradient image (a plane or constant): "
            "nothing to register"
        )
    if gradient != "none":
        fraction = stats.nonzero / grad.size
        if fraction < MIN_TEXTURE_FRACTION:
            raise NearlyBlankError(
                f"{name} is nearly blank: only {100 * fraction:.2f} % of its gradient image "
                f"is non-zero (need {100 * MIN_TEXTURE_FRACTION:g} %): nothing to register"
            )


#: A nearly blank frame is measured when the whole-image alignment locks onto it
#: with at least this significance in both the levelled heights and the
#: x-gradient (one 11×11 feature on a flat 129×128 frame: z 128; HS-AFM frame 27
#: against its neighbours, scattered quantisation steps: z ≤ 4.1).
BLANK_LOCK_Z = 20.0


def allow_nearly_blank(
    err: NearlyBlankError,
    reference: npt.NDArray[np.floating] | None,
    current: npt.NDArray[np.floating],
    *,
    enabled: bool = True,
) -> None:
    """Re-raise ``err`` unless the two frames lock strongly onto each other
    (:data:`BLANK_LOCK_Z`): a few features on a flat background can be
    registered, scattered isolated steps cannot. Without a reference or with
    the coarse alignment disabled, the frame is refused."""
    if not enabled or reference is None:
        raise err
    # The frames' borders are flat here (nearly blank): no taper is needed,
    # and a taper lowers a sparse frame's z (64² rectangle: 42 → 15).
    lock = coarse_shift(reference, current, taper=False)
    if not (lock.trusted and min(lock.peak_z, lock.gradient_z) >= BLANK_LOCK_Z):
        raise err


def _check_values(arr: npt.NDArray[np.floating], name: str, lo: float, hi: float) -> None:
    """Refuse NaN/Inf pixels or a constant image, given the image's minimum
    ``lo`` and maximum ``hi`` (NaN or ±inf there when such pixels exist)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        finite = np.isfinite(arr)
        bad = int(arr.size - np.count_nonzero(finite))
        r, c = np.argwhere(~finite)[0]
        raise InvalidFrameError(
            f"{name} has {bad} NaN/Inf pixel(s), first at [row {r}, col {c}] = {arr[r, c]}"
        )
    if lo == hi:
        raise InvalidFrameError(f"{name} is constant (all pixels = {lo}): nothing to register")


def check_prior(prior_px: tuple[float, float] | None) -> tuple[float, float] | None:
    """Validate an expected drift ``(dx, dy)`` in px."""
    if prior_px is None:
        return None
    try:
        prior = (float(prior_px[0]), float(prior_px[1]))
    except (TypeError, ValueError, IndexError):
        raise RegistrationError(f"prior_px must be an (dx, dy) pair, got {prior_px!r}") from None
    if not all(math.isfinite(v) for v in prior):
        raise RegistrationError(f"prior_px must be finite, got {prior_px!r}")
    return prior

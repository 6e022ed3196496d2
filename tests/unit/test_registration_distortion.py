"""Non-rigid frames and large shifts over small overlaps (issue 38).

A bowed fast axis or bowed lines are not disagreement: the answer keeps to a
σ that carries the distortion, and is refused only past an eighth of a block.
Large shifts whose overlap is small are found where the overlap fits clearly
better, and refused where the sample's content repeats.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmdrift.registration import measure_drift
from afmdrift.registration._distortion import distortion_limit_px
from afmdrift.testing import add_noise, distorted_crop, distortion_field, terrace_texture

FRAME = (256, 256)


@pytest.fixture(scope="module")
def facets() -> np.ndarray:
    return terrace_texture((384, 384), pixel_size_nm=2.0, rng=np.random.default_rng(38))


def _pair(
    tex: np.ndarray, d: tuple[float, float], kind: str, amp: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ref = add_noise(distorted_crop(tex, FRAME), snr=10.0, rng=rng)
    cur = distorted_crop(tex, FRAME, dx_px=d[0], dy_px=d[1], kind=kind, amplitude_px=amp)
    return ref, add_noise(cur, snr=10.0, rng=rng)


def test_the_distortion_field_is_zero_mean_and_has_its_range() -> None:
    for kind in ("bow_x", "bow_y", "rotation", "creep"):
        dx, dy = distortion_field((128, 160), kind, 6.0)
        assert abs(dx.mean()) < 1e-9
        assert abs(dy.mean()) < 1e-9
        span = max(np.ptp(dx), np.ptp(dy))
        assert span == pytest.approx(6.0, rel=0.05), kind
    with pytest.raises(ValueError, match="unknown distortion"):
        distortion_field((64, 64), "twist", 1.0)


@pytest.mark.parametrize(("kind", "amp"), [("bow_x", 1.0), ("bow_x", 6.0), ("bow_y", 8.0)])
def test_a_bowed_frame_keeps_to_its_sigma(facets: np.ndarray, kind: str, amp: float) -> None:
    """A fast axis (or lines) bowed by 1–8 px across the frame: valid, off
    the frame's mean shift by at most 3σ on each axis, and says how far its
    parts moved apart (``distortion_px``). Before, a 1 px bow was 8σ off."""
    d = (4.3, -7.1)
    ref, cur = _pair(facets, d, kind, amp, seed=int(amp * 10))
    r = measure_drift(ref, cur, pixel_size_nm=2.0)
    assert r.valid, r.reason
    assert r.distortion_px is not None
    axis = 0 if kind == "bow_x" else 1
    assert r.distortion_px[axis] > 0.2 * amp
    sig = (r.sigma_x_nm / 2.0, r.sigma_y_nm / 2.0)
    for got, want, s in zip((r.dx_px, r.dy_px), d, sig, strict=True):
        assert abs(got - want) <= 3 * s + 0.02, (got, want, s)


def test_a_rigid_frame_is_not_called_distorted(facets: np.ndarray) -> None:
    ref, cur = _pair(facets, (4.3, -7.1), "bow_x", 0.0, seed=1)
    r = measure_drift(ref, cur, pixel_size_nm=2.0)
    assert r.valid
    assert r.distortion_px is None
    assert math.hypot(r.dx_px - 4.3, r.dy_px + 7.1) < 0.05


def test_a_distortion_past_an_eighth_of_a_block_is_refused_saying_why(facets: np.ndarray) -> None:
    """A fast axis bowed by 24 px across a 256² frame (32 px blocks): its
    parts moved apart by about 7 px RMS, past the 4 px limit."""
    assert distortion_limit_px(32) == 4.0
    ref, cur = _pair(facets, (4.3, -7.1), "bow_x", 24.0, seed=2)
    r = measure_drift(ref, cur, pixel_size_nm=2.0)
    assert not r.valid
    assert r.reason is not None
    assert "non-rigid" in r.reason, r.reason
    assert "no single shift" in r.reason


def _natural_pair(name: str, n: int, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
    import skimage.data
    from skimage.color import rgb2gray

    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if img.ndim == 3:
        img = rgb2gray(img[..., :3])
    if name == "retina":
        img = img[250:1150, 250:1150]
    x0, y0 = max(0, ix), max(0, iy)
    ref = img[y0 : y0 + n, x0 : x0 + n]
    cur = img[y0 - iy : y0 - iy + n, x0 - ix : x0 - ix + n]
    return ref.copy(), cur.copy()


def test_a_large_shift_over_a_small_overlap_is_found() -> None:
    """450² crops of a retina photograph (100, 350) px apart: 17 % of the
    area overlaps. A smooth background correlates over the minimal-image
    overlap (60 %) at NCC 0.45; the true one fits at 1.0 and wins."""
    ref, cur = _natural_pair("retina", 450, 100, 350)
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx((100.0, 350.0), abs=0.1)
    assert "overlap of" in r.prior


def test_a_sample_that_repeats_itself_is_refused_not_guessed() -> None:
    """scikit-image's grass photograph matches itself at an offset of about
    (181, 346) px: 256² crops (−131, −193) px apart (12 % overlapping, NCC
    0.99) have a second match at (51, 153) (40 %, NCC 0.66), on which 11
    blocks agreed. Both are named; neither is given as the drift."""
    ref, cur = _natural_pair("grass", 256, -131, -193)
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert not r.valid
    assert r.reason is not None
    assert r.reason.startswith("ambiguous: two shifts fit"), r.reason
    assert "(-131, -193)" in r.reason

"""Whole-image coarse alignment (:func:`afmdrift.registration.coarse_shift`), the
prior of ``measure_drift`` and of ``afmdrift measure``; ground truth built here."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.registration import RegistrationConfig, coarse_shift, measure_drift
from afmdrift.registration._coarse import COARSE_MIN_GRADIENT_Z, COARSE_MIN_Z, static_pixels
from afmdrift.testing import (
    Particles,
    band_limit,
    fourier_shift,
    rough_texture,
    terrace_texture,
)

SIZE = 256


def _texture(seed: int = 0) -> np.ndarray:
    """Random rough surface, 5 nm rms, 4 px correlation length."""
    rng = np.random.default_rng(seed)
    return rough_texture(
        (SIZE, SIZE), pixel_size_nm=1.0, rng=rng, rms_nm=5.0, correlation_length_nm=4.0
    )


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved so that a feature at u appears at u + (dx, dy) (periodic)."""
    return fourier_shift(img, dx_px=dx, dy_px=dy)


def test_coarse_shift_integer_and_significance() -> None:
    ref = _texture(seed=9)
    c = coarse_shift(ref, _shifted(ref, 17.0, -23.0))
    assert (c.dx_px, c.dy_px) == (17.0, -23.0)
    assert c.peak_z > 3 * COARSE_MIN_Z
    assert c.gradient_z > 3 * COARSE_MIN_GRADIENT_Z
    assert c.trusted
    noise = coarse_shift(_texture(seed=10), _texture(seed=11))
    assert noise.peak_z < COARSE_MIN_Z
    assert not noise.trusted


def test_coarse_streaks_are_not_trusted() -> None:
    """Regression: scan-line streaks (here a random tilt per line, different in each
    frame, as on HS-AFM frames 22-31) gave a strong levelled-height peak at a
    spurious shift but no x-gradient support; they must not steer the search.
    Each correlation value is now in deviations of its own row and column
    too, and streaks raise whole rows: with or without the taper the peak is
    the shift (within a pixel), or it is not trusted."""
    rng = np.random.default_rng(12)
    x = np.arange(SIZE) - SIZE / 2

    def streaks() -> np.ndarray:
        return rng.normal(size=(SIZE, 1)) * x[None, :] * (5.0 / SIZE)

    texture = _texture(seed=13)
    ref, cur = texture + streaks(), _shifted(texture, 0.3, 0.2) + streaks()
    for c in (coarse_shift(ref, cur, taper=False), coarse_shift(ref, cur)):
        assert not c.trusted or max(abs(c.dx_px - 0.3), abs(c.dy_px - 0.2)) <= 1, c
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx((0.3, 0.2), abs=0.1)


def test_measure_drift_uses_the_coarse_prior_beyond_the_block_search() -> None:
    """A 40 px shift is beyond the ±32 px block search: measure_drift finds it
    only through its coarse prior, and not at all with coarse = false."""
    ref = _texture(seed=14)
    cur = _shifted(ref, -40.4, 12.2)
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert abs(r.dx_px + 40.4) < 0.1
    assert abs(r.dy_px - 12.2) < 0.1
    blind = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(coarse=False))
    assert not (blind.valid and abs(blind.dx_px + 40.4) < 1.0)


def test_a_thin_wrapped_strip_does_not_outweigh_a_partly_changed_frame() -> None:
    """Regression (issue 29): frames whose content wraps around (a circular
    shift) with a quarter of the current frame replaced. The wrapped
    alternative ``d + N`` overlaps in a thin unchanged strip whose NCC beat
    the partly changed minimal-image overlap's; it was taken, every block
    window left the frame, and the pair was refused with 0 of 64 blocks."""
    size = 512
    ref = rough_texture(
        (size, size), pixel_size_nm=1.0, rng=np.random.default_rng(29), rms_nm=5.0,
        correlation_length_nm=4.0,
    )  # fmt: skip
    cur = _shifted(ref, 4.0, -22.0)
    quarter = cur[: size // 2, : size // 2]
    cur[: size // 2, : size // 2] = np.roll(quarter[:, ::-1], (70, 130), axis=(0, 1))
    c = coarse_shift(ref, cur)
    assert (c.dx_px, c.dy_px) == (4.0, -22.0)
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert abs(r.dx_px - 4.0) < 0.05
    assert abs(r.dy_px + 22.0) < 0.05


def _smooth_with_bumps(seed: int = 21) -> np.ndarray:
    """A smooth background (correlation length 60 px) 30 times the height of
    six sharp bumps, 320²."""
    rng = np.random.default_rng(seed)
    bg = rough_texture(
        (320, 320), pixel_size_nm=1.0, rng=rng, rms_nm=30.0, correlation_length_nm=60.0
    )
    bumps = Particles(
        x_px=rng.uniform(0, 320, 6), y_px=rng.uniform(0, 320, 6),
        height_nm=np.full(6, 1.0), fwhm_px=3.0,
    )  # fmt: skip
    return bg + band_limit(bumps.render((320, 320)))


@pytest.mark.parametrize("d", [(9, -14), (-17, 6), (12, 11), (-5, -19)])
def test_frame_edges_do_not_make_the_coarse_peak_of_a_smooth_texture(d: tuple[int, int]) -> None:
    """Regression (issue 29): on 212² frames of a smooth background with a few
    sharp features, integer shifts, no noise, the whole-frame phase
    correlation peaked within a pixel of zero (the wrap-around jumps and
    corners, which both frames share, carry its whitened spectrum) and the
    blocks, searching around zero, were refused. With the borders tapered
    the peak is the shift."""
    tex = _smooth_with_bumps()
    m = 54
    ref = tex[m : m + 212, m : m + 212]
    cur = tex[m - d[1] : m - d[1] + 212, m - d[0] : m - d[0] + 212]
    whole = coarse_shift(ref, cur, taper=False)
    assert max(abs(whole.dx_px), abs(whole.dy_px)) <= 1  # the edges' peak
    c = coarse_shift(ref, cur)
    assert (c.dx_px, c.dy_px) == d
    assert c.trusted
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx(d, abs=0.05)


@pytest.mark.parametrize("seed", [2, 10])
def test_shift_of_most_of_the_frame_both_ways_is_found_by_the_whole_frame_correlation(
    seed: int,
) -> None:
    """A shift of 350 px of 450² frames both ways leaves a 100² overlap in
    the corner the taper fades out: the tapered correlation's trusted peak is
    elsewhere, the blocks fail around it, and the whole-frame correlation,
    tried then, finds the overlap, which is measured."""
    img = terrace_texture((800, 800), pixel_size_nm=2.0, rng=np.random.default_rng(seed))
    ref, cur = img[0:450, 0:450], img[350:800, 350:800]
    tapered = coarse_shift(ref, cur)
    assert tapered.trusted
    assert (tapered.dx_px, tapered.dy_px) != (-350.0, -350.0)
    r = measure_drift(ref, cur, pixel_size_nm=2.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx((-350.0, -350.0), abs=0.05)
    assert "untapered" in r.prior


@pytest.mark.parametrize("d", [(8, 8), (-8, 8), (8, -8), (-8, -8)])
def test_equal_flat_background_is_not_static_structure(d: tuple[int, int]) -> None:
    """Regression (issue 29): a bright rectangle on a dark 64² frame moved
    diagonally (OpenCV's case). The frames are equal on the flat background,
    which was taken for static structure: the masked correlation left out
    all but the rectangle's edges, found nothing, and the frame was refused
    as nearly blank. Where the phase correlation finds a shift away from
    zero, the equal pixels did not decide it."""
    r1, r2 = np.zeros((64, 64)), np.zeros((64, 64))
    r1[22:36, 20:40] = 1.0
    r2[22 + d[1] : 36 + d[1], 20 + d[0] : 40 + d[0]] = 1.0
    assert static_pixels(r1, r2) is not None
    c = coarse_shift(r1, r2)
    assert c.method == "phase"
    assert (c.dx_px, c.dy_px) == d
    r = measure_drift(r1, r2, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx(d, abs=0.05)


def test_masked_correlation_of_a_small_negative_shift() -> None:
    """Regression: the masked correlation read the x-gradient's correlation,
    a column narrower than the heights', at the heights' wrapped index, past
    its end for dx = −1 (IndexError)."""
    big = _texture(seed=0)
    ref, cur = big[20:236, 20:236].copy(), big[20:236, 21:237].copy()  # dx = -1
    for img in (ref, cur):
        img[:30, :] = 0.0  # a static border
    c = coarse_shift(ref, cur)
    assert c.method == "masked"
    assert (c.dx_px, c.dy_px) == (-1.0, 0.0)
    r = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert r.valid, r.reason
    assert (r.dx_px, r.dy_px) == pytest.approx((-1.0, 0.0), abs=0.05)

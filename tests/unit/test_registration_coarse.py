"""Whole-image coarse alignment (:func:`afmdrift.registration.coarse_shift`), the
prior of ``measure_drift`` and of ``afmdrift measure``; ground truth built here."""

from __future__ import annotations

import numpy as np

from afmdrift.registration import RegistrationConfig, coarse_shift, measure_drift
from afmdrift.registration._coarse import COARSE_MIN_GRADIENT_Z, COARSE_MIN_Z
from afmdrift.testing import fourier_shift, rough_texture

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
    frame, as on HS-AFM frames 22-31) give a strong levelled-height peak at a
    spurious shift but no x-gradient support; they must not steer the search."""
    rng = np.random.default_rng(12)
    x = np.arange(SIZE) - SIZE / 2

    def streaks() -> np.ndarray:
        return rng.normal(size=(SIZE, 1)) * x[None, :] * (5.0 / SIZE)

    texture = _texture(seed=13)
    c = coarse_shift(texture + streaks(), _shifted(texture, 0.3, 0.2) + streaks())
    assert c.peak_z >= COARSE_MIN_Z
    assert abs(c.dy_px) > 10  # the spurious peak the levelled heights pick
    assert c.gradient_z < COARSE_MIN_GRADIENT_Z
    assert not c.trusted


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

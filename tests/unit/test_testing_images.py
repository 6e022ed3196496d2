"""The synthetic textures and exact shifts of afmdrift.testing (ground truth of
the registration tests, so they are tested first)."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.testing import (
    Particles,
    add_line_offsets,
    add_noise,
    add_plane,
    fourier_shift,
    particle_texture,
    rough_texture,
    shifted_crop,
    terrace_texture,
)

TEXTURES = {
    "particles": particle_texture,
    "terraces": terrace_texture,
    "rough": rough_texture,
}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12)


def test_integer_fourier_shift_is_a_roll(rng: np.random.Generator) -> None:
    img = rough_texture((64, 96), pixel_size_nm=2.0, rng=rng)
    shifted = fourier_shift(img, dx_px=5, dy_px=-3)
    np.testing.assert_allclose(shifted, np.roll(img, (-3, 5), axis=(0, 1)), atol=1e-12)


@pytest.mark.parametrize("name", sorted(TEXTURES))
def test_two_half_pixel_shifts_make_one_pixel(name: str, rng: np.random.Generator) -> None:
    """Sub-pixel shifts are exact for every texture (it is band-limited enough)."""
    img = TEXTURES[name]((128, 128), pixel_size_nm=2.0, rng=rng)
    twice = fourier_shift(fourier_shift(img, dx_px=0.5, dy_px=0.25), dx_px=0.5, dy_px=0.75)
    ref = np.roll(img, (1, 1), axis=(0, 1))
    assert np.max(np.abs(twice - ref)) < 1e-9 * np.ptp(img)


@pytest.mark.parametrize("name", sorted(TEXTURES))
def test_fractional_shift_matches_direct_resampling(name: str, rng: np.random.Generator) -> None:
    """A shift by 0.5 px lands between the samples: compare with the mean of
    the neighbours, which a smooth texture must approach (no ringing)."""
    img = TEXTURES[name]((128, 128), pixel_size_nm=2.0, rng=rng)
    half = fourier_shift(img, dx_px=0.5, dy_px=0.0)
    linear = 0.5 * (img + np.roll(img, 1, axis=1))
    assert np.std(half - linear) < 0.1 * np.std(img)


def test_shifted_crop_moves_content_without_wraparound(rng: np.random.Generator) -> None:
    tex = particle_texture((200, 220), pixel_size_nm=2.0, rng=rng)
    a = shifted_crop(tex, shape=(100, 120))
    b = shifted_crop(tex, shape=(100, 120), dx_px=7, dy_px=-4)
    # A feature at (x, y) in a is at (x + 7, y - 4) in b.
    np.testing.assert_allclose(b[0:96, 7:120], a[4:100, 0:113], atol=1e-9)
    # What enters at the left edge is texture, not wrapped-around frame content.
    np.testing.assert_allclose(b[:, :7], tex[54:154, 43:50], atol=1e-9)


def test_shifted_crop_refuses_shift_beyond_margin(rng: np.random.Generator) -> None:
    tex = rough_texture((120, 120), pixel_size_nm=2.0, rng=rng)
    with pytest.raises(ValueError, match="exceeds the texture margin"):
        shifted_crop(tex, shape=(100, 100), dx_px=11.0)
    with pytest.raises(ValueError, match="does not fit"):
        shifted_crop(tex, shape=(130, 100))


def test_particles_render_at_their_positions() -> None:
    p = Particles(
        x_px=np.array([20.25, 70.0]),
        y_px=np.array([30.0, 10.5]),
        height_nm=np.array([30.0, 20.0]),
        fwhm_px=8.0,
    )
    img = p.render((64, 96))
    sigma = 8.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    assert img[30, 20] == pytest.approx(30.0 * np.exp(-0.5 * (0.25 / sigma) ** 2), rel=1e-9)
    assert np.unravel_index(np.argmax(img), img.shape) == (30, 20)
    # Half maximum at half the FWHM (4 px) from the centre of the second one.
    assert img[10, 74] == pytest.approx(0.5 * 20.0 * np.exp(-0.5 * (0.5 / sigma) ** 2), rel=0.05)
    # Periodic: a particle near the edge wraps around.
    edge = Particles(np.array([1.0]), np.array([1.0]), np.array([5.0]), 8.0).render((32, 32))
    assert edge[1, 31] > 0.5 * edge[1, 1]


def test_particle_texture_has_about_the_requested_density(rng: np.random.Generator) -> None:
    p = Particles.random((500, 500), pixel_size_nm=2.0, rng=rng, density_per_um2=100.0)
    assert 70 <= p.x_px.size <= 130  # 1 µm² · 100 / µm², Poisson
    assert p.fwhm_px == pytest.approx(15.0)


def test_terraces_are_flat_levels_one_step_apart(rng: np.random.Generator) -> None:
    h = terrace_texture((256, 256), pixel_size_nm=2.0, rng=rng, roughness_nm=0.0)
    levels = (h - h.min()) / 0.335
    frac = np.abs(levels - np.rint(levels))
    assert np.mean(frac < 0.1) > 0.8  # most pixels sit on a terrace
    assert np.ptp(h) >= 2 * 0.335


def test_noise_follows_the_snr_definition(rng: np.random.Generator) -> None:
    img = rough_texture((256, 256), pixel_size_nm=2.0, rng=rng, rms_nm=3.0)
    noisy = add_noise(img, snr=10.0, rng=rng)
    assert np.std(noisy - img) == pytest.approx(0.3, rel=0.03)
    with pytest.raises(ValueError, match="snr"):
        add_noise(img, snr=0.0, rng=rng)


def test_plane_and_line_offsets(rng: np.random.Generator) -> None:
    img = np.zeros((4, 5))
    tilted = add_plane(img, offset_nm=1.0, slope_x=0.5, slope_y=-2.0)
    assert tilted[3, 4] == pytest.approx(1.0 + 2.0 - 6.0)
    lines = add_line_offsets(img, rms_nm=1.0, rng=rng)
    assert np.allclose(np.ptp(lines, axis=1), 0.0)
    assert np.ptp(lines[:, 0]) > 0

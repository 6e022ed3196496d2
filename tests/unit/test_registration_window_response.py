"""Blocks whose texture is not spread evenly over their window: each block's
window response is measured and divided out, and its vector applies where
its texture is. Ground truth is built here (Fourier-shifted particle frames)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from afmdrift.registration import RegistrationConfig
from afmdrift.registration._blocks import config_for_image
from afmdrift.registration._engine import BlockEngine, ReferenceSpectra
from afmdrift.testing import fourier_shift, rough_texture


def _sparse_particles(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Gaussian particles (σ 3 px, 5 nm high) about 40 px apart on flat ground:
    most 64 px windows hold one or two, anywhere in the window. The border
    is flat, so a circular shift brings nothing in."""
    y, x = np.mgrid[:size, :size].astype(np.float64)
    h = np.zeros((size, size))
    for cy in range(32, size - 24, 40):
        for cx in range(32, size - 24, 40):
            if rng.random() < 0.5:
                continue
            py, px = cy + rng.uniform(-14, 14), cx + rng.uniform(-14, 14)
            h += 5.0 * np.exp(-((x - px) ** 2 + (y - py) ** 2) / 18.0)
    return h


def _engine_and_reference(image: np.ndarray) -> tuple[BlockEngine, ReferenceSpectra, np.ndarray]:
    cfg = config_for_image(RegistrationConfig(), image)
    engine = BlockEngine(image.shape, cfg)
    grad = engine.prepare(image)[0].copy()
    return engine, engine.reference(grad), grad


def _textured(engine: BlockEngine, grad: np.ndarray, ref: ReferenceSpectra) -> np.ndarray:
    """Blocks whose window holds a particle (window-weighted gradient energy
    above 5 % of the largest)."""
    ey, ex = engine.layout.ext
    w2 = engine.window.astype(np.float64) ** 2
    energy = np.array(
        [
            np.sum(
                w2 * (grad[t : t + ey, lf : lf + ex] - grad[t : t + ey, lf : lf + ex].mean()) ** 2
            )
            for t, lf in zip(ref.top, ref.left, strict=True)
        ]
    )
    textured: np.ndarray = energy > 0.05 * energy.max()
    return textured


def _both_ways(
    engine: BlockEngine, ref: ReferenceSpectra, grad: np.ndarray
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Block vectors and measured flags of ``grad`` against ``ref`` as it is
    (calibrated) and with its window response left out."""
    uncorrected = dataclasses.replace(
        ref, unbias=np.tile(np.eye(2), (engine.layout.n_blocks, 1, 1))
    )
    out = {}
    for name, reference in (("calibrated", ref), ("uncorrected", uncorrected)):
        meas, _, _ = engine.measure(reference, grad, prior_px=(0.0, 0.0))
        out[name] = (meas.vectors_px, meas.measured)
    return out


@pytest.mark.parametrize("shift", [0.5, -0.5, 0.3])
def test_a_lone_particle_in_its_window_is_not_pulled_towards_the_window(shift: float) -> None:
    """Regression: a block whose texture is one particle read a half-pixel
    shift up to 0.05 px short (towards the shift its window was placed at),
    and the same block did so in every frame: on 256² gold-on-mica sessions
    up and down frames came out 0.4 nm apart. The measured window response
    divides it out."""
    rng = np.random.default_rng(1)
    image = _sparse_particles(rng) + 0.01 * rng.standard_normal((256, 256))
    engine, ref, grad = _engine_and_reference(image)
    textured = _textured(engine, grad, ref)
    assert textured.sum() >= 30
    current = fourier_shift(image, dx_px=shift, dy_px=shift) + 0.01 * rng.standard_normal(
        (256, 256)
    )
    cur_grad = engine.prepare(current)[0].copy()
    errors = {
        name: np.abs(vectors[measured & textured] - shift).max()
        for name, (vectors, measured) in _both_ways(engine, ref, cur_grad).items()
    }
    assert errors["calibrated"] <= 0.015, errors
    assert errors["uncorrected"] >= 0.025, errors  # the effect this test guards against


@pytest.mark.parametrize("correlation_px", [4.0, 20.0])
def test_a_smooth_texture_read_through_its_window_response_loses_the_pixel_pull(
    correlation_px: float,
) -> None:
    """A texture as smooth as a fifth of the window (the x gradient of heights
    correlated over 20 px in 64 px windows) read half-pixel shifts 0.06 px
    RMS short, up to 0.2 px in one block; a rough one (4 px) 0.003 px. The
    measured response takes out most of either."""
    rng = np.random.default_rng(3)
    image = rough_texture(
        (256, 256), pixel_size_nm=1.0, rng=rng, rms_nm=2.0, correlation_length_nm=correlation_px
    )
    engine, ref, _ = _engine_and_reference(image)
    cur_grad = engine.prepare(fourier_shift(image, dx_px=0.5, dy_px=0.5))[0].copy()
    rms = {}
    for name, (vectors, measured) in _both_ways(engine, ref, cur_grad).items():
        assert measured.all()
        rms[name] = float(np.sqrt(np.mean((vectors - 0.5) ** 2)))
    assert rms["calibrated"] <= 0.01, rms
    assert rms["calibrated"] <= 0.2 * rms["uncorrected"], rms


def test_a_block_vector_applies_where_its_texture_is() -> None:
    """One particle off-centre in a window: the block's weight centre (where
    its vector applies in time) is the particle, not the window's centre."""
    size = 256
    y, x = np.mgrid[:size, :size].astype(np.float64)
    at = (100.0, 84.0)  # (x, y)
    image = 5.0 * np.exp(-((x - at[0]) ** 2 + (y - at[1]) ** 2) / 18.0)
    image += 0.001 * np.random.default_rng(0).standard_normal((size, size))
    engine, ref, grad = _engine_and_reference(image)
    ex = engine.layout.ext[1]
    centres = np.asarray(ref.weight_centres_px)
    textured = _textured(engine, grad, ref)
    assert textured.any()
    # every window holding the particle puts its vector at the particle
    # (within the x-gradient's half-pixel offset and the window's weighting)
    assert np.abs(centres[textured] - np.array(at)).max() < 3.0
    # while the windows' own centres are up to half a window away
    assert np.abs(engine.centres_px[textured] - np.array(at)).max() > ex / 4


def test_three_point_peak_models_are_not_calibrated() -> None:
    """Their pixel-locking bias is not linear in the shift: a response measured
    at 1 px would be wrong at a fraction of one, so they are left as they are."""
    rng = np.random.default_rng(3)
    image = rough_texture((256, 256), pixel_size_nm=1.0, rng=rng, rms_nm=2.0)
    cfg = config_for_image(RegistrationConfig(subpixel="sinc"), image)
    engine = BlockEngine(image.shape, cfg)
    ref = engine.reference(engine.prepare(image)[0].copy())
    np.testing.assert_array_equal(ref.unbias, np.tile(np.eye(2), (engine.layout.n_blocks, 1, 1)))


def test_the_window_response_can_be_turned_off() -> None:
    """``window_response = false`` (for reference = consecutive, where every
    frame pays the two calibration passes): no correction."""
    rng = np.random.default_rng(1)
    image = _sparse_particles(rng)
    cfg = config_for_image(RegistrationConfig(window_response=False), image)
    engine = BlockEngine(image.shape, cfg)
    ref = engine.reference(engine.prepare(image)[0].copy())
    np.testing.assert_array_equal(ref.unbias, np.tile(np.eye(2), (engine.layout.n_blocks, 1, 1)))


@pytest.mark.parametrize("angle_deg", [0.0, 40.0])
def test_straight_edges_are_not_amplified(angle_deg: float) -> None:
    """Regression (review): a straight terrace step reads nothing along itself
    (the aperture problem), so its response is near 1 in that direction and
    ``I − B`` near singular: the correction was allowed when every entry of
    ``B`` was ≤ 0.5 (``B = [[.5, .5], [.5, .5]]`` made ``inv`` raise, 40°
    steps gave 5× amplification). A block is now corrected only where no
    direction reads less than half of itself: at most 2× its noise."""
    size = 256
    y, x = np.mgrid[:size, :size].astype(np.float64)
    th = np.deg2rad(angle_deg)
    u = x * np.cos(th) + y * np.sin(th)
    image = 0.35 * np.floor(u / 90.0) + 0.35 / (1.0 + np.exp(-((u % 90.0) - 45.0) / 1.5))
    image += 0.002 * np.random.default_rng(0).standard_normal(image.shape)
    _, ref, _ = _engine_and_reference(image)
    unbias = np.asarray(ref.unbias)
    assert np.isfinite(unbias).all()
    assert np.linalg.norm(unbias, 2, axis=(1, 2)).max() <= 2.0 + 1e-9


def test_calibrating_a_calibrated_reference_measures_it_afresh() -> None:
    """Regression (review): ``calibrate`` measured through the reference's own
    correction, so a second call undid the first."""
    rng = np.random.default_rng(3)
    image = rough_texture(
        (256, 256), pixel_size_nm=1.0, rng=rng, rms_nm=2.0, correlation_length_nm=20.0
    )
    engine, ref, _ = _engine_and_reference(image)
    again = engine.calibrate(ref)
    np.testing.assert_allclose(again.unbias, ref.unbias, atol=1e-9)
    assert np.abs(np.asarray(ref.unbias) - np.eye(2)).max() > 0.1  # there is a correction

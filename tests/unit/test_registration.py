"""Accuracy and robustness of measure_drift (block phase correlation).

Ground truth is built here: frames are cut from exactly shifted copies of a
larger synthetic texture (afmdrift.testing), so content enters and leaves at
the frame edges as in a real scan. SNR = std of heights / std of noise.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from afmdrift.errors import InputError
from afmdrift.registration import (
    DriftResult,
    InvalidFrameError,
    RegistrationConfig,
    RegistrationError,
    measure_drift,
)
from afmdrift.testing import (
    Particles,
    add_line_offsets,
    add_noise,
    add_plane,
    particle_texture,
    rough_texture,
    shifted_crop,
    terrace_texture,
)

PIXEL_NM = 2.0


@pytest.fixture(scope="module")
def particles_640() -> np.ndarray:
    return particle_texture((640, 640), pixel_size_nm=PIXEL_NM, rng=np.random.default_rng(7))


def _pair(
    tex: np.ndarray,
    d: tuple[float, float],
    *,
    shape: tuple[int, int] = (512, 512),
    snr: float | None = 10.0,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    ref = shifted_crop(tex, shape=shape)
    cur = shifted_crop(tex, shape=shape, dx_px=d[0], dy_px=d[1])
    if snr is not None:
        assert rng is not None
        ref = add_noise(ref, snr=snr, rng=rng)
        cur = add_noise(cur, snr=snr, rng=rng)
    return ref, cur


@pytest.mark.slow
def test_pure_translation_at_snr10_is_within_005_px_rms(particles_640: np.ndarray) -> None:
    """50 random sub-pixel shifts within ±40 px, 512×512 frames, SNR 10."""
    rng = np.random.default_rng(1)
    errors = []
    for _ in range(50):
        d = rng.uniform(-40.0, 40.0, 2)
        ref, cur = _pair(particles_640, (d[0], d[1]), rng=rng)
        r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
        assert r.valid, r.reason
        errors.append((r.dx_px - d[0], r.dy_px - d[1]))
    rms = math.sqrt(float(np.mean(np.square(errors))))
    assert rms <= 0.05, f"RMS error {rms:.4f} px"


@pytest.mark.parametrize(
    ("name", "texture"),
    [("terraces", terrace_texture), ("rough", rough_texture)],
)
def test_other_textures_register(
    name: str,
    texture,
) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(3)
    kwargs = {"terrace_width_nm": 40.0} if name == "terraces" else {}
    tex = texture((640, 640), pixel_size_nm=PIXEL_NM, rng=rng, **kwargs)
    errors = []
    for _ in range(4):
        d = rng.uniform(-20.0, 20.0, 2)
        ref, cur = _pair(tex, (d[0], d[1]), rng=rng)
        r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
        assert r.valid, r.reason
        errors.append((r.dx_px - d[0], r.dy_px - d[1]))
    assert np.max(np.abs(errors)) < 0.1, errors


def test_sign_convention_feature_moves_by_plus_d(particles_640: np.ndarray) -> None:
    """A particle at u in the reference is at u + d in the current frame."""
    ref, cur = _pair(particles_640, (5.0, -3.0), snr=None)
    r = measure_drift(ref, cur, pixel_size_nm=(2.0, 3.0))
    assert r.dx_px == pytest.approx(5.0, abs=0.02)
    assert r.dy_px == pytest.approx(-3.0, abs=0.02)
    assert r.dx_nm == pytest.approx(10.0, abs=0.04)
    assert r.dy_nm == pytest.approx(-9.0, abs=0.06)  # y uses its own pixel size


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_is_preserved_and_results_agree(
    particles_640: np.ndarray, dtype: type[np.floating]
) -> None:
    rng = np.random.default_rng(5)
    ref, cur = _pair(particles_640, (3.3, -1.7), rng=rng)
    r64 = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    ref_t, cur_t = ref.astype(dtype), cur.astype(dtype)
    before = cur_t.copy()
    r = measure_drift(ref_t, cur_t, pixel_size_nm=PIXEL_NM)
    np.testing.assert_array_equal(cur_t, before)  # inputs untouched
    for arr in (r.field.vectors_px, r.field.centres_px, r.field.confidence, r.field.mse):
        assert arr.dtype == dtype
    assert r.dx_px == pytest.approx(r64.dx_px, abs=2e-3)
    assert r.dy_px == pytest.approx(r64.dy_px, abs=2e-3)


def test_z_offset_tilt_and_line_offsets_do_not_change_the_result(
    particles_640: np.ndarray,
) -> None:
    """Regression guard for the gradient image and mean removal: a z offset,
    a tilt plane and per-line offsets added to one frame leave the drift as is."""
    rng = np.random.default_rng(11)
    ref, cur = _pair(particles_640, (7.4, 2.2), rng=rng)
    base = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    spoiled = add_plane(cur, offset_nm=250.0, slope_x=0.8, slope_y=-0.5)
    spoiled = add_line_offsets(spoiled, rms_nm=3.0, rng=rng)
    r = measure_drift(ref, spoiled, pixel_size_nm=PIXEL_NM)
    assert r.valid_blocks == base.valid_blocks
    assert r.dx_px == pytest.approx(base.dx_px, abs=1e-3)
    assert r.dy_px == pytest.approx(base.dy_px, abs=1e-3)
    assert abs(base.dx_px - 7.4) < 0.05
    assert abs(base.dy_px - 2.2) < 0.05


def test_line_offsets_would_hurt_without_the_x_gradient(particles_640: np.ndarray) -> None:
    """The invariance above comes from the x gradient: heights ('none') are hurt.

    The coarse alignment levels the lines itself and the MSE check still
    picks the right peaks, so the damage shows in the block stage: fewer
    blocks agree and the uncertainty grows tenfold (measured: 46 against 59
    valid blocks, sigma 0.18 against 0.017 nm)."""
    rng = np.random.default_rng(12)
    ref, cur = _pair(particles_640, (7.4, 2.2), rng=rng)
    cur = add_line_offsets(cur, rms_nm=8.0, rng=rng)
    with_grad = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    without = measure_drift(
        ref, cur, pixel_size_nm=PIXEL_NM, config=RegistrationConfig(gradient="none")
    )
    assert with_grad.valid, with_grad.reason
    assert math.hypot(with_grad.dx_px - 7.4, with_grad.dy_px - 2.2) < 0.05
    assert without.valid_blocks < with_grad.valid_blocks - 5
    assert not without.valid or without.sigma_nm > 5 * with_grad.sigma_nm


@pytest.mark.parametrize("gradient", ["x", "y", "both", "none"])
def test_every_gradient_mode_measures_a_shift(particles_640: np.ndarray, gradient: str) -> None:
    rng = np.random.default_rng(13)
    ref, cur = _pair(particles_640, (-4.6, 6.1), rng=rng, snr=30.0)
    r = measure_drift(
        ref, cur, pixel_size_nm=PIXEL_NM, config=RegistrationConfig(gradient=gradient)
    )
    assert r.valid, r.reason
    assert r.dx_px == pytest.approx(-4.6, abs=0.1)
    assert r.dy_px == pytest.approx(6.1, abs=0.1)


def _altered_pair(
    d: tuple[float, float], *, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames in which particles in 16 of the 64 blocks of the current frame
    were pushed by the tip (moved together by 2 px) or added, as in Figs. 2
    and 7 of Yang et al. (2008). Returns (reference, current, altered mask)."""
    canvas = (640, 640)
    origin = 64
    parts = Particles.random(canvas, pixel_size_nm=PIXEL_NM, rng=rng, density_per_um2=150.0)
    ref = parts.render(canvas)[origin : origin + 512, origin : origin + 512]
    x = parts.x_px + d[0]
    y = parts.y_px + d[1]
    cells = rng.choice(64, size=16, replace=False)
    altered = np.zeros((8, 8), dtype=bool)
    altered.flat[cells] = True
    cx = np.floor((x - origin) / 64).astype(int)
    cy = np.floor((y - origin) / 64).astype(int)
    inside = (cx >= 0) & (cx < 8) & (cy >= 0) & (cy < 8)
    moved = np.zeros(x.size, dtype=bool)
    moved[inside] = altered[cy[inside], cx[inside]]
    x = np.where(moved, x + 2.0, x)
    y = np.where(moved, y - 1.0, y)
    # Two new particles in each altered block.
    add_cells = np.repeat(cells, 2)
    ax = origin + 64 * (add_cells % 8) + rng.uniform(8, 56, add_cells.size)
    ay = origin + 64 * (add_cells // 8) + rng.uniform(8, 56, add_cells.size)
    cur_parts = Particles(
        x_px=np.concatenate([x, ax]),
        y_px=np.concatenate([y, ay]),
        height_nm=np.concatenate([parts.height_nm, np.full(ax.size, 30.0)]),
        fwhm_px=parts.fwhm_px,
    )
    cur = cur_parts.render(canvas)[origin : origin + 512, origin : origin + 512]
    return add_noise(ref, snr=20.0, rng=rng), add_noise(cur, snr=20.0, rng=rng), altered


@pytest.mark.slow
def test_quarter_of_blocks_altered_stays_within_01_px() -> None:
    """Blocks with moved/added particles are rejected; the drift stays right."""
    rng = np.random.default_rng(21)
    worst = 0.0
    for _ in range(4):
        d = (float(rng.uniform(-10, 10)), float(rng.uniform(-10, 10)))
        ref, cur, _ = _altered_pair(d, rng=rng)
        r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
        assert r.valid, r.reason
        assert r.valid_blocks <= r.total_blocks - 8  # altered blocks were dropped
        worst = max(worst, abs(r.dx_px - d[0]), abs(r.dy_px - d[1]))
    assert worst <= 0.1, worst


@pytest.mark.slow
def test_whole_frame_phase_correlation_fails_on_altered_frames() -> None:
    """The same frames fool whole-frame phase correlation (scikit-image, and
    our engine with a single frame-sized block): why the paper uses blocks."""
    from skimage.registration import phase_cross_correlation

    rng = np.random.default_rng(21)
    sk_worst = 0.0
    one_block_worst = 0.0
    one_block = RegistrationConfig(
        block_size=512, extended_size=512, min_valid_blocks=2, coarse=False
    )
    for _ in range(4):
        d = (float(rng.uniform(-10, 10)), float(rng.uniform(-10, 10)))
        ref, cur, _ = _altered_pair(d, rng=rng)
        # skimage returns the shift that registers `moving` onto `reference`.
        shift, _, _ = phase_cross_correlation(cur, ref, upsample_factor=100)
        sk_worst = max(sk_worst, abs(shift[1] - d[0]), abs(shift[0] - d[1]))
        r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM, config=one_block)
        if r.valid:
            one_block_worst = max(one_block_worst, abs(r.dx_px - d[0]), abs(r.dy_px - d[1]))
        else:
            one_block_worst = math.inf
    assert sk_worst > 0.1, sk_worst
    assert one_block_worst > 0.1, one_block_worst


def test_mad_rule_drops_the_altered_blocks() -> None:
    rng = np.random.default_rng(22)
    d = (4.2, -6.3)
    ref, cur, _ = _altered_pair(d, rng=rng)
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    assert r.valid, r.reason
    assert r.dx_px == pytest.approx(d[0], abs=0.1)
    assert r.dy_px == pytest.approx(d[1], abs=0.1)
    off = np.hypot(*(r.field.vectors_px - np.array(d)).T) > 0.5
    assert off[r.field.measured].sum() >= 8  # there were outliers ...
    assert not np.any(r.field.valid & off)  # ... and none of them was kept


def test_paper_rule_end_to_end_on_a_clean_pair(particles_640: np.ndarray) -> None:
    rng = np.random.default_rng(23)
    ref, cur = _pair(particles_640, (-12.6, 3.3), rng=rng)
    cfg = RegistrationConfig(outlier_rule="paper", epsilon_px=0.5)
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM, config=cfg)
    assert r.valid, r.reason
    assert r.valid_blocks >= 40
    assert r.dx_px == pytest.approx(-12.6, abs=0.05)
    assert r.dy_px == pytest.approx(3.3, abs=0.05)
    dist = np.hypot(*(r.field.vectors_px - [r.dx_px, r.dy_px]).T)
    assert np.all(dist[r.field.valid] <= 0.5 + 0.1)


@pytest.mark.parametrize(
    ("shape", "tol_px"),
    [((256, 512), 0.05), ((200, 200), 0.05), ((100, 300), 0.2), ((64, 64), 0.3)],
)
def test_frames_not_a_multiple_of_the_block_size(
    particles_640: np.ndarray, shape: tuple[int, int], tol_px: float
) -> None:
    """Windows always lie inside the frame; 512×256, 200×200 and tiny frames
    work. Frames not taller than one window cannot move their windows with the
    drift, which costs accuracy (see docs/registration.md)."""
    rng = np.random.default_rng(31)
    tex = (
        particles_640
        if min(shape) > 64
        else rough_texture((160, 160), pixel_size_nm=PIXEL_NM, rng=rng, correlation_length_nm=8.0)
    )
    ref, cur = _pair(tex, (2.7, -1.4), shape=shape, rng=rng, snr=20.0)
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    assert r.valid, r.reason
    assert r.dx_px == pytest.approx(2.7, abs=tol_px)
    assert r.dy_px == pytest.approx(-1.4, abs=tol_px)
    cx, cy = r.field.centres_px.T
    assert cx.min() > 0
    assert cx.max() < shape[1]
    assert cy.min() > 0
    assert cy.max() < shape[0]


def test_uncertainty_reflects_the_block_spread(particles_640: np.ndarray) -> None:
    rng = np.random.default_rng(41)
    ref, cur = _pair(particles_640, (1.3, 0.4), rng=rng)
    r = measure_drift(ref, cur, pixel_size_nm=(2.0, 4.0))
    v = r.field.vectors_px[r.field.valid]
    assert r.sigma_x_nm == pytest.approx(
        2.0 * np.std(v[:, 0], ddof=1) / math.sqrt(r.valid_blocks), rel=0.5
    )
    assert r.sigma_x_nm > 0
    assert r.sigma_y_nm > 0
    assert r.sigma_nm == pytest.approx(math.sqrt(0.5 * (r.sigma_x_nm**2 + r.sigma_y_nm**2)))
    assert r.valid_blocks == int(r.field.valid.sum())
    assert r.total_blocks == 64


@pytest.mark.parametrize("shape", [(256, 256), (200, 200), (512, 128)])
def test_unrelated_frames_are_flagged_invalid_not_a_number(shape: tuple[int, int]) -> None:
    """Regression guard: frames with nothing in common once produced a 'valid'
    drift from three overlapping windows that agreed on a false peak."""
    rng = np.random.default_rng(51)
    for other_texture in (particle_texture, rough_texture, terrace_texture):
        ref = add_noise(particle_texture(shape, pixel_size_nm=PIXEL_NM, rng=rng), snr=10, rng=rng)
        other = add_noise(other_texture(shape, pixel_size_nm=PIXEL_NM, rng=rng), snr=10, rng=rng)
        r = measure_drift(ref, other, pixel_size_nm=PIXEL_NM)
        assert not r.valid, (r.dx_px, r.dy_px, r.valid_blocks)
        assert r.reason is not None
        assert "blocks valid" in r.reason or "disagree" in r.reason
        assert math.isnan(r.dx_px)
        assert math.isnan(r.dy_nm)
        d = r.to_dict()
        assert d["valid"] is False
        assert d["dx_px"] is None
        json.dumps(d)


def test_to_dict_is_json_ready(particles_640: np.ndarray) -> None:
    ref, cur = _pair(particles_640, (1.0, 2.0), snr=None)
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    d = json.loads(json.dumps(r.to_dict()))
    for key in ("dx_px", "dy_px", "dx_nm", "dy_nm", "sigma_nm", "valid_blocks", "total_blocks"):
        assert key in d
    assert d["valid"] is True
    assert isinstance(r, DriftResult)


def test_prior_extends_the_range_beyond_the_search_window(particles_640: np.ndarray) -> None:
    rng = np.random.default_rng(61)
    ref, cur = _pair(particles_640, (55.3, -48.8), rng=rng)
    no_coarse = RegistrationConfig(coarse=False)
    blind = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM, config=no_coarse)
    assert not blind.valid or abs(blind.dx_px - 55.3) > 1.0
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM, config=no_coarse, prior_px=(53, -50))
    assert r.dx_px == pytest.approx(55.3, abs=0.05)
    assert r.dy_px == pytest.approx(-48.8, abs=0.05)


# -- bad input ---------------------------------------------------------------------


@pytest.fixture
def good() -> np.ndarray:
    return rough_texture((96, 96), pixel_size_nm=PIXEL_NM, rng=np.random.default_rng(0))


def test_nan_pixel_is_rejected_with_its_position(good: np.ndarray) -> None:
    bad = good.copy()
    bad[5, 7] = np.nan
    with pytest.raises(InvalidFrameError, match=r"NaN/Inf.*row 5, col 7"):
        measure_drift(good, bad, pixel_size_nm=PIXEL_NM)
    bad[5, 7] = np.inf
    with pytest.raises(InvalidFrameError, match="current"):
        measure_drift(good, bad, pixel_size_nm=PIXEL_NM)


def test_constant_and_textureless_images_are_rejected(good: np.ndarray) -> None:
    with pytest.raises(InvalidFrameError, match="constant"):
        measure_drift(np.full_like(good, 3.0), good, pixel_size_nm=PIXEL_NM)
    plane = add_plane(np.zeros_like(good), slope_x=0.5, slope_y=0.2)
    with pytest.raises(InvalidFrameError, match="no texture"):
        measure_drift(good, plane, pixel_size_nm=PIXEL_NM)


@pytest.mark.parametrize("gradient", ["x", "y", "both", "none"])
@pytest.mark.parametrize("where", [(0, 0), (95, 95), (0, 95), (95, 0), (40, 50)])
def test_a_nan_pixel_anywhere_is_rejected_in_every_gradient_mode(
    good: np.ndarray, gradient: str, where: tuple[int, int]
) -> None:
    """Corners included: the "both" gradient never reads the last row and
    column together, yet a NaN there must still be refused."""
    bad = good.copy()
    bad[where] = np.nan
    cfg = RegistrationConfig(gradient=gradient)  # type: ignore[arg-type]
    with pytest.raises(InvalidFrameError, match=rf"current has 1 NaN/Inf.*row {where[0]}"):
        measure_drift(good, bad, pixel_size_nm=PIXEL_NM, config=cfg)


def test_heights_whose_differences_overflow_float32_are_rejected(good: np.ndarray) -> None:
    """Finite float64 heights far outside any nm range give infinite float32
    differences: refused with the height range named, not measured."""
    huge = good * 1e40
    with pytest.raises(InvalidFrameError, match="beyond the float32 range"):
        measure_drift(good, huge, pixel_size_nm=PIXEL_NM)


def test_nearly_blank_frame_is_rejected(good: np.ndarray) -> None:
    """A flat frame with a few isolated pixel steps (1 % of its x-gradient
    non-zero) is refused: a handful of deltas once gave agreeing blocks."""
    blank = np.zeros_like(good)
    blank.flat[np.random.default_rng(1).choice(blank.size, 40, replace=False)] = 0.06
    with pytest.raises(InvalidFrameError, match=r"nearly blank.*%"):
        measure_drift(good, blank, pixel_size_nm=PIXEL_NM)


def test_flat_windows_are_not_measured_and_raise_no_warnings(
    particles_640: np.ndarray,
) -> None:
    """Regression: a window whose gradient is exactly zero has an all-zero
    spectrum; normalising it overflowed (numpy RuntimeWarnings, errors in
    this suite). Its blocks must simply not be measured while the textured
    rest of the frame still gives the drift."""
    ref, cur = _pair(particles_640, (3.3, -1.6), rng=np.random.default_rng(5))
    ref[:, :200] = 7.0  # the left 200 columns flat in both frames
    cur[:, :200] = 7.0
    r = measure_drift(ref, cur, pixel_size_nm=PIXEL_NM)
    assert r.valid, r.reason
    assert abs(r.dx_px - 3.3) < 0.05
    assert abs(r.dy_px + 1.6) < 0.05
    left = r.field.centres_px[:, 0] < 100
    assert left.any()
    assert not r.field.measured[left].any()


def test_shape_mismatch_names_both_shapes(good: np.ndarray) -> None:
    with pytest.raises(RegistrationError, match=r"\(96, 96\).*\(96, 80\)"):
        measure_drift(good, good[:, :80], pixel_size_nm=PIXEL_NM)


@pytest.mark.parametrize("shape", [(63, 100), (100, 10)])
def test_too_small_images_are_rejected(shape: tuple[int, int]) -> None:
    img = np.random.default_rng(0).standard_normal(shape)
    with pytest.raises(InvalidFrameError, match=r"too small.*64"):
        measure_drift(img, img, pixel_size_nm=PIXEL_NM)


@pytest.mark.parametrize(
    "bad_input", [np.zeros((2, 96, 96)), np.zeros((96, 96), dtype=complex), "image"]
)
def test_non_image_inputs_are_rejected(good: np.ndarray, bad_input: object) -> None:
    with pytest.raises(InvalidFrameError):
        measure_drift(good, bad_input, pixel_size_nm=PIXEL_NM)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "pixel", [0.0, -1.0, math.nan, math.inf, (1.0, 0.0), (1.0,), "2 nm", (1.0, 2.0, 3.0)]
)
def test_invalid_pixel_size_is_rejected(good: np.ndarray, pixel: object) -> None:
    with pytest.raises(RegistrationError, match="pixel_size_nm"):
        measure_drift(good, good, pixel_size_nm=pixel)  # type: ignore[arg-type]


def test_errors_are_input_errors() -> None:
    assert issubclass(RegistrationError, InputError)
    assert issubclass(InvalidFrameError, RegistrationError)
    assert issubclass(InvalidFrameError, ValueError)


def test_config_rejects_inconsistent_sizes() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="extended_size"):
        RegistrationConfig(block_size=128, extended_size=64)
    with pytest.raises(ValidationError, match="block_search_px"):
        RegistrationConfig(block_search_px=63)

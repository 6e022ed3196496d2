"""Rendering of simulated frames: sub-pixel accuracy, per-pixel timing, manipulation,
scan-direction bias."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from scipy import ndimage, optimize
from skimage.registration import phase_cross_correlation

from afmdrift.drivers import ScanDirection
from afmdrift.drivers.sim import Sample, Scenario, SimulatedAFM, parse_scenario

QUIET: dict[str, Any] = {"thermal": {"enabled": False}}


def gold_scenario(**overrides: Any) -> Scenario:
    """Noise-free gold particles on a perfectly flat substrate, no drift unless asked."""
    data: dict[str, Any] = {
        "scan": {"pixels": [128, 128], "size_nm": [512.0, 512.0], "line_rate_hz": 64.0},
        "sample": {
            "map_px": 512,
            "grid_nm": 4.0,
            "roughness_nm": 0.0,
            "gold": {"density_per_um2": 40.0},
        },
        "physics": dict(QUIET),
        "artefacts": {"noise_nm": 0.0},
    }
    data.update(overrides)
    return parse_scenario(data)


def analytic_heights(
    sample: Sample, sx: npt.NDArray[np.float64], sy: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Exact sum of the particles' Gaussians (periodic images) at sample positions."""
    out = np.zeros(np.broadcast(sx, sy).shape)
    ex, ey = sample.extent_nm
    for x, y, d in sample.particles:
        sig_x, sig_y = sample.particle_sigma_px(float(d))
        dx = (sx - x + 0.5 * ex) % ex - 0.5 * ex
        dy = (sy - y + 0.5 * ey) % ey - 0.5 * ey
        out += d * np.exp(
            -0.5
            * ((dx / (sig_x * sample.grid_nm[0])) ** 2 + (dy / (sig_y * sample.grid_nm[1])) ** 2)
        )
    return out


def fit_shift_px(
    reference: npt.NDArray[np.float64],
    moving: npt.NDArray[np.float64],
    *,
    margin: int = 8,
    start: tuple[float, float] = (0.0, 0.0),
) -> tuple[float, float]:
    """Shift (dx, dy) in px with moving(u) = reference(u - d), by least squares on the interior
    (local: ``start`` must be within about a pixel)."""
    inner = (slice(margin, -margin), slice(margin, -margin))
    coeffs = ndimage.spline_filter(reference, order=3)

    def residual(d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        shifted = ndimage.shift(coeffs, (d[1], d[0]), order=3, prefilter=False)
        return (shifted[inner] - moving[inner]).ravel()  # type: ignore[no-any-return]

    fit = optimize.least_squares(residual, x0=np.array(start), x_scale=1.0)
    return float(fit.x[0]), float(fit.x[1])


def pixel_grid(sim: SimulatedAFM) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    cols, rows = sim.pixels
    px, py = sim.pixel_size_nm
    return np.arange(cols)[None, :] * px, np.arange(rows)[:, None] * py


def test_rendering_matches_the_analytic_surface_to_far_below_a_pixel() -> None:
    """Guards the <0.05 px accuracy: the interpolated map equals the analytic surface."""
    step = (1.37, -2.61)  # nm; a constant drift from t = 0 (a tip change at power-on)
    sc = gold_scenario(
        physics={
            **QUIET,
            "tip_changes": {"enabled": True, "scheduled": [{"t_s": 0.0, "step_nm": list(step)}]},
        }
    )
    sim = SimulatedAFM(sc, seed=3)
    frame = sim.advance_to(2.5)[0]
    ux, uy = pixel_grid(sim)
    expected = analytic_heights(sim.sample, ux - step[0], uy - step[1])
    err = frame.heights_nm - expected
    slope = np.hypot(*np.gradient(expected, *sim.pixel_size_nm[::-1]))
    # Height error expressed as a lateral error where the surface is steep.
    steep = slope > 0.5
    assert steep.sum() > 500
    lateral_px = np.abs(err[steep]) / slope[steep] / sim.pixel_size_nm[0]
    assert np.percentile(lateral_px, 99) < 0.01
    assert np.abs(err).max() < 0.05


def test_constant_drift_is_an_exact_subpixel_shift() -> None:
    """A frame under constant drift d is the zero-drift frame shifted by d (registration view).

    The scan pixel (3 nm) differs from the sample grid (4 nm), so the frames
    sample the surface between its grid nodes and the shift is measured with a
    different interpolant than the renderer's.
    """
    step = (3.3, -5.1)  # nm = (1.1, -1.7) px
    scan = {"pixels": [128, 128], "size_nm": [384.0, 384.0], "line_rate_hz": 64.0}
    base = SimulatedAFM(gold_scenario(scan=scan), seed=11).advance_to(2.5)[0]
    shifted_sc = gold_scenario(
        scan=scan,
        physics={
            **QUIET,
            "tip_changes": {"enabled": True, "scheduled": [{"t_s": 0.0, "step_nm": list(step)}]},
        },
    )
    shifted = SimulatedAFM(shifted_sc, seed=11).advance_to(2.5)[0]
    dx, dy = fit_shift_px(base.heights_nm, shifted.heights_nm)
    assert dx == pytest.approx(step[0] / 3.0, abs=0.01)
    assert dy == pytest.approx(step[1] / 3.0, abs=0.01)


def test_within_frame_drift_distorts_the_frame_pixel_by_pixel() -> None:
    """Each pixel is measured at its own time: rows and pixels along a line see p(t)."""
    sc = gold_scenario(
        scan={"pixels": [96, 96], "size_nm": [384.0, 384.0], "line_rate_hz": 8.0},
        physics={
            **QUIET,
            # tau >> frame: about (A/tau) = (2, -1) nm/s
            "warmup": {"enabled": True, "amplitude_nm": [1.728e5, -0.864e5], "tau_s": 86400.0},
        },
    )
    sim = SimulatedAFM(sc, seed=2)
    up, down = sim.advance_to(24.5)[:2]
    assert (up.direction, down.direction) == (ScanDirection.UP, ScanDirection.DOWN)
    ux, uy = pixel_grid(sim)
    cols, rows = sim.pixels
    line_s = 1.0 / 8.0
    for frame in (up, down):
        k = np.arange(rows) if frame.direction is ScanDirection.UP else rows - 1 - np.arange(rows)
        t = (
            frame.t_start_s
            + k[:, None] * line_s
            + (np.arange(cols)[None, :] + 0.5) / cols * 0.5 * line_s
        )
        px, py = sim.truth_at(t)
        expected = analytic_heights(sim.sample, ux - px, uy - py)
        assert np.abs(frame.heights_nm - expected).max() < 0.05
        # The distortion is real: ignoring the within-frame timing is far off.
        t_mid = np.full_like(t, frame.t_mid_s)
        qx, qy = sim.truth_at(t_mid)
        assert np.abs(frame.heights_nm - analytic_heights(sim.sample, ux - qx, uy - qy)).max() > 1.0


def test_scan_direction_bias_alternates_between_up_and_down_frames() -> None:
    bias = (2.0, 6.0)  # nm: up frames +b/2, down frames -b/2
    sc = gold_scenario(
        physics={**QUIET, "scan_direction": {"enabled": True, "bias_nm": list(bias)}}
    )
    frames = SimulatedAFM(sc, seed=4).advance_to(4 * 2.0 + 0.1)
    assert [f.direction.value for f in frames] == ["up", "down", "up", "down"]
    for a, b in itertools.pairwise(frames):
        dx, dy = fit_shift_px(a.heights_nm, b.heights_nm)
        sign = 1.0 if b.direction is ScanDirection.UP else -1.0
        assert dx == pytest.approx(sign * bias[0] / 4.0, abs=0.01)
        assert dy == pytest.approx(sign * bias[1] / 4.0, abs=0.01)


def test_manipulation_changes_only_the_blocks_around_the_push() -> None:
    sim = SimulatedAFM(gold_scenario(), seed=8)
    before = sim.advance_to(2.0)[0].heights_nm
    # Find a particle inside the frame and push it 60 nm along +x.
    k, _ = sim.sample.nearest_particle(256.0, 256.0)
    x, y, _ = sim.sample.particles[k]
    moved = sim.manipulate(float(x) - 20.0, float(y), float(x) + 60.0, float(y))
    assert moved >= 1
    after = sim.advance_to(4.0 + 2.0)[-1].heights_nm
    diff = np.abs(after - before)
    assert diff.max() > 10.0  # the particle is 30 nm high
    blocks = diff.reshape(4, 32, 4, 32).max(axis=(1, 3))  # 4x4 blocks of 32x32 px
    changed = blocks > 1e-6
    assert 1 <= changed.sum() <= 4
    assert sim.events[-1].kind.value == "manipulation"


def texture_scenario(path: str, pixel_nm: float, **scan: Any) -> Scenario:
    return parse_scenario(
        {
            "scan": {"pixels": [64, 64], "size_nm": [64 * pixel_nm, 64 * pixel_nm], **scan},
            "sample": {
                "kind": "texture",
                "edge_sigma_px": 0.5,
                "texture": {"path": path, "pixel_size_nm": [pixel_nm, pixel_nm]},
            },
            "physics": dict(QUIET),
            "artefacts": {"noise_nm": 0.0},
        }
    )


def test_texture_is_made_periodic_without_seams(tmp_path: Any) -> None:
    from afmdrift.drivers.sim._sample import periodic_component

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:160, 0:160]
    image = 0.05 * xx + 0.02 * yy + ndimage.gaussian_filter(rng.standard_normal((160, 160)), 3)
    per = periodic_component(image)
    jump_before = np.abs(image[:, 0] - image[:, -1]).mean()
    jump_after = np.abs(per[:, 0] - per[:, -1]).mean()
    inner_step = np.abs(np.diff(per, axis=1)).mean()
    assert jump_before > 5.0
    assert jump_after < jump_before / 50
    assert jump_after < 5 * inner_step  # the wrap-around edge is like an ordinary pixel step
    # The texture is used as is otherwise: a zero-drift frame on the texture grid
    # reproduces its periodic part exactly.
    np.save(tmp_path / "tex.npy", image)
    sim = SimulatedAFM(texture_scenario(str(tmp_path / "tex.npy"), 2.0), seed=0)
    frame = sim.advance_to(64 / 4.0 + 0.1)[0]  # default 4 Hz
    expected = per - per.mean()
    np.testing.assert_allclose(frame.heights_nm, expected[:64, :64], atol=1e-6)


def test_bad_texture_file_names_the_key(tmp_path: Any) -> None:
    from afmdrift.errors import ConfigError

    np.save(tmp_path / "flat.npy", np.zeros(10))
    with pytest.raises(ConfigError, match=r"sample\.texture\.path"):
        SimulatedAFM(texture_scenario(str(tmp_path / "flat.npy"), 2.0))


@pytest.mark.realdata
@pytest.mark.slow
def test_real_nanoscope_image_as_texture(real_file: Any, tmp_path: Any) -> None:
    """A real AFM image drives the simulator through afmdrift.io (pixel size from the file)."""
    path = real_file("nanoscope3a_15um.002")
    sc = parse_scenario(
        {
            "scan": {"pixels": [96, 96], "size_nm": [96 * 58.59375, 96 * 58.59375]},
            "sample": {"kind": "texture", "texture": {"path": str(path)}},
            "physics": dict(QUIET),
            "artefacts": {"noise_nm": 0.0},
        }
    )
    sim = SimulatedAFM(sc, seed=0)
    assert sim.sample.grid_nm == pytest.approx((58.59375, 58.59375), rel=1e-3)
    frame = sim.advance_to(96 / 4.0 + 0.1)[0]
    assert np.isfinite(frame.heights_nm).all()
    assert frame.heights_nm.std() > 0.1


def test_offset_move_of_plus_delta_shows_features_at_u_minus_delta() -> None:
    """Sign convention: the window moves by +Δ over the sample; this is not drift."""
    delta = (10.4, -6.2)
    sim = SimulatedAFM(gold_scenario(), seed=12)
    sim.set_offset(*delta)
    frame = sim.advance_to(2.5)[0]
    ux, uy = pixel_grid(sim)
    expected = analytic_heights(sim.sample, ux + delta[0], uy + delta[1])
    assert np.abs(frame.heights_nm - expected).max() < 0.05
    assert sim.truth_at(2.5) == (0.0, 0.0)


def test_image_artefacts_noise_line_offsets_z_drift_and_tilt() -> None:
    """On a flat, empty sample every height comes from the artefacts, each with its signature."""
    sc = parse_scenario(
        {
            "scan": {"pixels": [128, 128], "size_nm": [512.0, 512.0], "line_rate_hz": 64.0},
            "sample": {"map_px": 512, "roughness_nm": 0.0, "gold": {"density_per_um2": 0.0}},
            "physics": dict(QUIET),
            "artefacts": {
                "noise_nm": 0.2,
                "line_offset_nm": 0.5,
                "z_drift_nm_per_s": 0.25,
                "tilt": [0.01, -0.004],
            },
        }
    )
    sim = SimulatedAFM(sc, seed=1)
    frames = sim.advance_to(2 * 2.0 + 0.01)
    h = frames[0].heights_nm
    ux, uy = pixel_grid(sim)
    t_mid = frames[0].row_times_s()[:, None]  # z is sampled once per line
    plane = 0.01 * ux - 0.004 * uy
    resid = h - plane - 0.25 * t_mid
    # Line offsets: a constant per row (std 0.5 nm); noise: white within a row (std 0.2 nm).
    row_means = resid.mean(axis=1)
    assert row_means.std() == pytest.approx(0.5, rel=0.2)
    within = resid - row_means[:, None]
    assert within.std() == pytest.approx(0.2, rel=0.05)
    # z drift: the mean height rises by rate x frame period from one frame to the next.
    d_mean = frames[1].heights_nm.mean() - frames[0].heights_nm.mean()
    assert d_mean == pytest.approx(0.25 * 2.0, abs=0.2)
    # Tilt: the mean slope along the fast axis is the x tilt.
    gx = np.polyfit(ux.ravel(), h.mean(axis=0), 1)[0]
    assert gx == pytest.approx(0.01, abs=5e-4)


def test_tip_change_with_a_blunter_tip_broadens_the_particles() -> None:
    """Apparent width σ = √(R_p R_t): doubling R_t doubles each particle's imaged volume."""
    sc = gold_scenario(
        physics={
            **QUIET,
            "tip_changes": {
                "enabled": True,
                "scheduled": [{"t_s": 2.0, "step_nm": [0.0, 0.0], "tip_radius_nm": 20.0}],
            },
        }
    )
    sim = SimulatedAFM(sc, seed=5)
    before, after = sim.advance_to(6.0)[:2]
    assert after.t_start_s >= 2.0
    ux, uy = pixel_grid(sim)
    assert np.abs(after.heights_nm - analytic_heights(sim.sample, ux, uy)).max() < 0.05
    ratio = after.heights_nm.sum() / before.heights_nm.sum()
    assert ratio == pytest.approx(2.0, rel=0.1)


def test_any_height_array_can_be_the_sample() -> None:
    rng = np.random.default_rng(2)
    image = ndimage.gaussian_filter(rng.standard_normal((200, 240)), 2.0)
    sample = Sample.from_image(image, pixel_size_nm=(2.0, 3.0), edge_sigma_px=0.5)
    assert sample.extent_nm == (480.0, 600.0)
    sc = gold_scenario(scan={"pixels": [32, 32], "size_nm": [64.0, 96.0], "line_rate_hz": 64.0})
    sim = SimulatedAFM(sc, seed=0, sample=sample)
    frame = sim.advance_to(0.6)[0]
    np.testing.assert_allclose(frame.heights_nm, sample.base_nm[:32, :32], atol=1e-9)
    with pytest.raises(ValueError, match="16x16"):
        Sample.from_image(np.zeros((8, 8)), pixel_size_nm=(1.0, 1.0))


def test_registered_shift_under_drift_follows_the_row_timing() -> None:
    """docs/physics.md: a feature found dy rows away was scanned dy*T_l later, so whole-frame
    registration measures p(t_mid' + dy T_l) - p(t_mid), not the mid-time increment."""
    sc = gold_scenario(
        scan={"pixels": [96, 96], "size_nm": [384.0, 384.0], "line_rate_hz": 8.0},
        physics={
            **QUIET,
            "warmup": {"enabled": True, "amplitude_nm": [2.592e5, -1.728e5], "tau_s": 86400.0},
        },
    )
    sim = SimulatedAFM(sc, seed=6)
    f0, _, f2 = sim.advance_to(3 * 12.0 + 0.1)[:3]
    assert f0.direction is f2.direction is ScanDirection.UP
    coarse, _, _ = phase_cross_correlation(f2.heights_nm, f0.heights_nm, normalization=None)
    start = (float(coarse[1]), float(coarse[0]))
    dx_px, dy_px = fit_shift_px(f0.heights_nm, f2.heights_nm, margin=24, start=start)
    measured = np.array([dx_px, dy_px]) * 4.0
    line_s = 1.0 / 8.0
    corrected = np.subtract(sim.truth_at(f2.t_mid_s + dy_px * line_s), sim.truth_at(f0.t_mid_s))
    naive = np.subtract(sim.truth_at(f2.t_mid_s), sim.truth_at(f0.t_mid_s))
    np.testing.assert_allclose(measured, corrected, atol=0.05 * 4.0)
    assert abs(measured[0] - naive[0]) > 4.0  # > 1 px: the effect is real

"""The compiled per-block kernels against plain NumPy statements of the same
arithmetic (afmdrift.registration._spectra, _peaks, _subpixel, _selection)."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmdrift.registration import _peaks, _selection, _spectra, _subpixel
from afmdrift.registration._constants import PeakConstants, SpectrumConstants, SubpixelConstants
from afmdrift.registration._passes import Peaks, Windows

RNG = np.random.default_rng(11)


def _interleaved(z: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(z, dtype=np.complex64).view(np.float32)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gradient_x_and_its_figures_match_numpy(dtype: type) -> None:
    """The gradient pass's image, non-zero count, finiteness and uniformity
    against NumPy, on heights with repeated values (zero differences)."""
    h = (np.round(RNG.standard_normal((70, 90)) * 2.0) / 2.0 + 1e3).astype(dtype)
    out = np.empty((70, 89), np.float32)
    finite, nonzero, uniform = _spectra.gradient_x(h, out)
    expect = (h[:, 1:] - h[:, :-1]).astype(np.float32)
    np.testing.assert_array_equal(out, expect)
    assert (finite, nonzero, uniform) == (True, np.count_nonzero(expect), False)
    assert 0 < nonzero < expect.size
    for r, c, bad in [(0, 0, np.nan), (69, 89, np.inf), (33, 44, -np.inf), (5, 89, np.nan)]:
        g = h.copy()
        g[r, c] = bad
        assert not _spectra.gradient_x(g, out)[0], (r, c, bad)
    plane = (np.arange(90)[None, :] * 3.0 + np.arange(70)[:, None] * 2.0).astype(dtype)
    assert _spectra.gradient_x(plane, out) == (True, out.size, True)
    assert _spectra.gradient_x(np.full((70, 90), 7.0, dtype), out) == (True, 0, True)
    if dtype is np.float64:  # finite heights whose differences overflow float32
        huge = np.where(np.arange(90) % 2 == 0, 3e38, -3e38)[None, :].repeat(70, axis=0)
        assert not _spectra.gradient_x(huge, out)[0]


def _normalise_numpy(spec: np.ndarray, eps_rel: float) -> tuple[np.ndarray, np.ndarray]:
    spec = spec.copy()
    spec[:, 0, 0] = 0.0  # the kernels zero the frequency the mean removal empties
    mag = np.abs(spec)
    floor = np.maximum(eps_rel * mag.reshape(len(spec), -1).max(axis=1), 1e-30)
    return spec / (mag + floor[:, None, None]), mag


def _spectrum_constants(ramp: np.ndarray, ky: int, kx: int) -> SpectrumConstants:
    """No window terms (the mean removal is tested through the engine)."""
    none = np.zeros(0, dtype=np.intp)
    return SpectrumConstants(
        w_rows=none,
        w_cols=none,
        w_vals=np.zeros((0, 2), dtype=np.float32),
        w_sum=1.0,
        eps_rel=1e-6,
        floor=1e-30,
        ky=ky,
        kx=kx,
        ramp=_interleaved(ramp),
    )


def _band_rows(rows: int, ky: int) -> np.ndarray:
    return np.r_[rows - ky : rows, 0 : ky + 1]


def test_normalise_reference_and_cross_match_the_numpy_statement() -> None:
    n, rows, cols = 3, 16, 24
    half = cols // 2 + 1
    ky, kx = 3, 4
    ref = np.fft.rfft2(RNG.standard_normal((n, rows, cols))).astype(np.complex64)
    cur = np.fft.rfft2(RNG.standard_normal((n, rows, cols))).astype(np.complex64)
    cur[1, 2, 3] = 0.0  # an exactly zero frequency stays finite

    ramp = np.exp(-2j * np.pi * RNG.random((rows, half))).astype(np.complex64)
    c = _spectrum_constants(ramp, ky, kx)
    ref_out = np.empty((n, rows, 2 * half), dtype=np.int16)
    ref_band = np.empty((n, 2 * ky + 1, kx + 1), dtype=np.float32)
    _spectra.normalise_reference(
        c, np.arange(n, dtype=np.intp), _interleaved(ref), ref_out, ref_band
    )
    want_ref, ref_mag = _normalise_numpy(ref, 1e-6)
    # Stored in fixed point: int16 multiples of 1 / 32767, rounded.
    fixed = ref_out.astype(np.float64) / _spectra.REF_SCALE
    ref_value = fixed[..., 0::2] + 1j * fixed[..., 1::2]
    np.testing.assert_allclose(ref_value, np.conj(want_ref) * ramp, rtol=0, atol=0.75 / 32767)
    np.testing.assert_allclose(ref_band, ref_mag[:, _band_rows(rows, ky), : kx + 1], rtol=1e-6)

    want_norm, cur_mag = _normalise_numpy(cur, 1e-6)
    want_cross = want_norm * ref_value
    # A batch holds the blocks in another order than the frame's arrays.
    order = np.array([2, 0, 1], dtype=np.intp)
    spec = _interleaved(cur[order])
    keep = np.empty((n, rows, 2 * half), dtype=np.int16)
    cur_band = np.empty_like(ref_band)
    band = np.empty((n, 2 * ky + 1, kx + 1), dtype=np.complex64)
    _spectra.normalise_cross(
        c, order, spec, ref_out, ref_band, keep, cur_band, band.view(np.float32)
    )
    back = np.argsort(order)
    spec = np.ascontiguousarray(spec.view(np.complex64)[back]).view(np.float32)
    band = band[back]
    # The kept spectra are ready to serve as the next reference.
    kept = keep.astype(np.float64) / _spectra.REF_SCALE
    kept_value = kept[..., 0::2] + 1j * kept[..., 1::2]
    np.testing.assert_allclose(kept_value, np.conj(want_norm) * ramp, rtol=0, atol=0.75 / 32767)
    np.testing.assert_allclose(spec.view(np.complex64), want_cross, rtol=5e-6, atol=1e-6)
    assert np.all(np.isfinite(spec))
    sel = np.ix_(range(n), _band_rows(rows, ky), range(kx + 1))
    np.testing.assert_allclose(cur_band, cur_mag[sel], rtol=1e-6)
    np.testing.assert_allclose(
        band, want_cross[sel] * cur_mag[sel] * ref_mag[sel], rtol=2e-5, atol=1e-3
    )


def _peaks_numpy(
    corr: np.ndarray, ry: int, rx: int, my: int, mx: int, k: int, ratio: float, nms: int
) -> list[tuple[int, int, float]]:
    """Greedy top-k with non-maximum suppression over shifts within (ry, rx);
    ``corr[iy, ix]`` is the correlation at shift ``(iy - my, ix - mx)``."""
    region = np.full((2 * my + 1, 2 * mx + 1), -np.inf, dtype=np.float32)
    for iy, ix in itertools.product(range(my - ry, my + ry + 1), range(mx - rx, mx + rx + 1)):
        region[iy, ix] = corr[iy, ix]
    found: list[tuple[int, int, float]] = []
    for _ in range(k):
        iy, ix = np.unravel_index(int(np.argmax(region)), region.shape)
        v = float(region[iy, ix])
        if found and not (v > 0 and v >= ratio * found[0][2]):
            break
        found.append((int(iy) - my, int(ix) - mx, v))
        if not v > 0:
            break
        region[max(0, iy - nms) : iy + nms + 1, max(0, ix - nms) : ix + nms + 1] = -np.inf
    return found


@pytest.mark.parametrize("search", [(9, 9), (4, 7)])
def test_pick_peaks_verifies_the_candidates_numpy_finds(search: tuple[int, int]) -> None:
    ry, rx = search
    my = mx = 9
    grad = RNG.standard_normal((120, 130)).astype(np.float32)
    ref_grad = RNG.standard_normal((120, 130)).astype(np.float32)
    n = 6
    corr = RNG.standard_normal((n, 2 * my + 1, 40)).astype(np.float32)
    # Several strong peaks per block, including ties and the search's edges.
    for i in range(n):
        for dy, dx in [(-3, 2), (5, -8), (0, 0), (-9, 9), (4, -7)]:
            corr[i, dy + my, dx + mx] = 20.0 + RNG.integers(0, 3)
    top = RNG.integers(20, 60, n).astype(np.intp)
    left = RNG.integers(20, 60, n).astype(np.intp)
    ref_top = top - RNG.integers(-3, 4, n)
    ref_left = left - RNG.integers(-3, 4, n)
    inner = np.array([8, 10], dtype=np.intp)
    lat_y = np.arange(0, 16, 3, dtype=np.intp)
    lat_x = np.arange(0, 20, 3, dtype=np.intp)
    c = PeakConstants(peaks=4, ratio=0.7, nms=2, inner=inner, mse_rows=lat_y, mse_cols=lat_x)
    out = Peaks.empty(n)
    order = RNG.permutation(n).astype(np.intp)  # the batch's order of the blocks
    _peaks.pick_peaks(
        c, order, corr[order], np.array([ry, rx, my, mx], dtype=np.intp),
        Windows(grad, top, left), Windows(ref_grad, ref_top, ref_left), out,
    )  # fmt: skip
    for i in range(n):
        cands = _peaks_numpy(corr[i], ry, rx, my, mx, 4, 0.7, 2)
        scored = []
        for sy, sx, v in cands:
            if not v > 0:
                continue
            y0, x0 = ref_top[i] + inner[0], ref_left[i] + inner[1]
            ty = y0 + (top[i] - ref_top[i]) + sy
            tx = x0 + (left[i] - ref_left[i]) + sx
            d = (
                grad[np.ix_(ty + lat_y, tx + lat_x)] - ref_grad[np.ix_(y0 + lat_y, x0 + lat_x)]
            ).astype(np.float64)
            scored.append((float(np.mean(d**2) - np.mean(d) ** 2), sy, sx, v))
        mse, sy, sx, v = min(scored, key=lambda t: t[0])  # first on ties, as the kernel
        assert (out.sy[i], out.sx[i]) == (sy, sx)
        assert out.peak[i] == np.float32(v)
        assert out.mse[i] == pytest.approx(mse, rel=1e-9, abs=1e-12)


def test_pick_peaks_without_a_positive_peak_reports_infinite_mse() -> None:
    corr = -np.ones((1, 9, 16), dtype=np.float32)
    corr[0, 5, 6] = -0.5  # shift (1, 2)
    grad = np.zeros((40, 40), dtype=np.float32)
    zero = np.zeros(1, dtype=np.intp)
    lattice = np.arange(0, 8, dtype=np.intp)
    c = PeakConstants(
        peaks=4, ratio=0.7, nms=2, inner=np.array([4, 4], dtype=np.intp), mse_rows=lattice,
        mse_cols=lattice,
    )  # fmt: skip
    out = Peaks.empty(1)
    _peaks.pick_peaks(
        c, zero, corr, np.array([4, 4, 4, 4], dtype=np.intp), Windows(grad, zero + 4, zero + 4),
        Windows(grad, zero, zero), out,
    )  # fmt: skip
    assert (out.sy[0], out.sx[0], out.peak[0]) == (1, 2, np.float32(-0.5))
    assert out.mse[0] == np.inf


@pytest.mark.parametrize(("dx", "dy"), [(0.0, 0.0), (0.37, -0.21), (-1.4, 2.2), (12.6, -7.45)])
@pytest.mark.parametrize("ramp", [(0, 0), (32, 20)])
def test_dft_subpixel_finds_the_shift_of_a_pure_translation_band(
    dx: float, dy: float, ramp: tuple[int, int]
) -> None:
    ey = ex = 64
    ky = kx = 8
    fy = np.arange(-ky, ky + 1) / ey
    fx = np.arange(0, kx + 1) / ex
    amp = np.exp(-((fy[:, None] * 9.0) ** 2) - (fx[None, :] * 9.0) ** 2)
    # R_k = A_k exp(-2πi k·d): the correlation peaks at +d; the reference's
    # phase ramp exp(-2πi k·m) moves it to d + m, which the kernel undoes.
    my, mx = ramp
    phase = fy[:, None] * (dy + my) + fx[None, :] * (dx + mx)
    band = (amp * np.exp(-2j * np.pi * phase))[None]
    peaks = Peaks.empty(1)
    peaks.sy[0], peaks.sx[0] = round(dy), round(dx)
    c = SubpixelConstants(
        method=0, fy=fy, fx=fx, shift=np.array(ramp, dtype=np.intp), envelope=np.zeros(2),
        scale=1.0,
    )  # fmt: skip
    _subpixel.dft_subpixel(c, np.zeros(1, np.intp), _interleaved(band), peaks)
    assert peaks.ok[0]
    assert peaks.sx[0] + peaks.fx[0] == pytest.approx(dx, abs=2e-4)
    assert peaks.sy[0] + peaks.fy[0] == pytest.approx(dy, abs=2e-4)


def test_mean_removal_leaves_an_exact_zero_frequency() -> None:
    """Regression: the zero frequency left by subtracting the window-weighted
    mean is rounding noise, which normalisation blew up to a unit term in
    every block's correlation (0.35 % of the peak on the HS-AFM movie with
    heights, enough to change one block's verified candidate)."""
    from afmdrift.registration._blocks import raised_cosine

    rows = cols = 32
    half = cols // 2 + 1
    window = raised_cosine(rows, cols)
    wspec = np.fft.rfft2(window.astype(np.float64))
    nz = np.abs(wspec) > 1e-9 * abs(wspec[0, 0])
    w_rows, w_cols = (a.astype(np.intp) for a in np.nonzero(nz))
    w_vals = np.column_stack([wspec[nz].real, wspec[nz].imag]).astype(np.float32)
    heights = 37.3 + RNG.standard_normal((2, rows, cols))  # a large mean, as heights have
    spec = np.fft.rfft2((heights * window).astype(np.float32)).astype(np.complex64)
    out = np.empty((2, rows, 2 * half), dtype=np.int16)
    band_mag = np.empty((2, 5, 3), dtype=np.float32)
    ramp = np.ones((rows, half), dtype=np.complex64)
    c = SpectrumConstants(
        w_rows=w_rows, w_cols=w_cols, w_vals=w_vals, w_sum=float(wspec[0, 0].real), eps_rel=1e-6,
        floor=1e-30, ky=2, kx=2, ramp=_interleaved(ramp),
    )  # fmt: skip
    _spectra.normalise_reference(c, np.arange(2, dtype=np.intp), _interleaved(spec), out, band_mag)
    assert np.all(out[:, 0, 0:2] == 0)
    assert np.all(band_mag[:, 2, 0] == 0)  # band row ky = 0
    # The other frequencies keep unit magnitude (the texture is still there).
    value = out.astype(np.float64) / _spectra.REF_SCALE
    assert np.abs(value[:, 1:, 0::2] + 1j * value[:, 1:, 1::2]).min() > 0.99


#: Run in a fresh interpreter (the kernels of this one are compiled by the
#: other tests): warm_up, then real frames; prints what each step compiled.
_WARM_UP_SCRIPT = """
import json, sys
import numpy as np
from numba.core.dispatcher import Dispatcher
from scipy.ndimage import gaussian_filter, shift
from afmdrift.registration import DriftTracker, RegistrationConfig, measure_drift, warm_up

def compiled():
    return {
        f"{name}.{attr}": sorted(map(str, obj.signatures))
        for name, module in list(sys.modules.items()) if name.startswith("afmdrift")
        for attr, obj in vars(module).items() if isinstance(obj, Dispatcher)
    }

config = RegistrationConfig.model_validate(json.loads(sys.argv[1]))
before = compiled()
warm_up(config)
warm = compiled()
# Frames unlike warm_up's pair: a smooth texture (the auto pre-filter picks the
# x gradient for it), another shape, both dtypes, with and without a prior.
base = gaussian_filter(np.random.default_rng(5).normal(size=(400, 480)), 2.0)
frames = [shift(base, (0.7 * k, -0.4 * k))[20:308, 20:404] for k in range(4)]
shifts = []
for dtype in (np.float32, np.float64):
    pair = (frames[0].astype(dtype), frames[1].astype(dtype))
    for prior in (None, (0.0, 0.0)):
        r = measure_drift(*pair, pixel_size_nm=2.0, config=config, prior_px=prior)
        shifts.append([r.dx_px, r.dy_px])
    tracker = DriftTracker(pixel_size_nm=2.0, config=config)
    for frame in frames:
        step = tracker.update(frame.astype(dtype))
    shifts.append(list(tracker.position_px))
after = compiled()
print(json.dumps({
    "before": sum(map(len, before.values())),
    "warm": sum(map(len, warm.values())),
    "shifts": shifts,
    "new": {k: sorted(set(v) - set(warm.get(k, []))) for k, v in after.items()
            if set(v) - set(warm.get(k, []))},
}))
"""


@pytest.mark.slow
@pytest.mark.parametrize(
    "config",
    [{}, {"subpixel": "sinc", "gradient": "none"}, {"reference": "consecutive", "threads": 1}],
)
def test_after_warm_up_real_frames_compile_no_kernel(config: dict[str, object]) -> None:
    """warm_up promises that the first real frame does not compile (or load)
    a kernel with the GIL held, so the daemon calls it before it publishes.
    Regression: its white-noise pair resolved gradient = "auto" to the
    levelled heights, so the compiled x-gradient pass, which smooth real
    textures get, was compiled on the first real frame."""
    done = subprocess.run(
        [sys.executable, "-c", _WARM_UP_SCRIPT, json.dumps(config)],
        cwd=Path(__file__).resolve().parents[2],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["before"] == 0  # importing compiles nothing: the check starts clean
    assert out["warm"] > 0
    # The frames were measured (drift -0.4 px in x, +0.7 px in y per frame;
    # without a pre-filter, sinc sub-pixel is within 0.15 px of it here).
    np.testing.assert_allclose(out["shifts"][0], [-0.4, 0.7], atol=0.25)
    np.testing.assert_allclose(out["shifts"][2], [-1.2, 2.1], atol=0.4)
    assert out["new"] == {}, out["new"]


@pytest.mark.parametrize("ddof", [1, 0])
@pytest.mark.parametrize("count", [0, 1, 2, 5, 64])
def test_masked_mean_std_matches_numpy(count: int, ddof: int) -> None:
    vectors = RNG.normal([3.0, -2.0], [0.4, 0.1], size=(64, 2))
    mask = np.zeros(64, dtype=bool)
    mask[RNG.choice(64, count, replace=False)] = True
    out = np.empty(4)
    _selection.masked_mean_std(vectors, mask, ddof, out)
    sel = vectors[mask]
    if count > 0:
        np.testing.assert_allclose(out[:2], sel.mean(axis=0), rtol=1e-13)
    else:
        assert np.isnan(out[:2]).all()
    if count > ddof:
        np.testing.assert_allclose(out[2:], sel.std(axis=0, ddof=ddof), rtol=1e-12, atol=1e-15)
    else:
        assert np.isnan(out[2:]).all()


def test_usable_blocks_prefers_placed_windows_and_falls_back() -> None:
    measured = np.array([1, 1, 1, 0, 1, 1], dtype=bool)
    placed = np.array([1, 1, 0, 1, 0, 1], dtype=bool)
    in_overlap = np.array([1, 1, 1, 1, 1, 0], dtype=bool)
    out = np.empty(6, dtype=bool)
    assert _selection.usable_blocks(measured, placed, in_overlap, 3, out) == placed.sum()
    np.testing.assert_array_equal(out, measured & placed)
    # Only 3 measured and placed: with 4 required, every measured block is
    # usable, and the blocks in the overlap are the ones available.
    assert _selection.usable_blocks(measured, placed, in_overlap, 4, out) == in_overlap.sum()
    np.testing.assert_array_equal(out, measured)


def test_masked_medians_returns_the_selected_count() -> None:
    vectors = np.array([[1.0, 5.0], [2.0, 6.0], [9.0, -1.0], [4.0, 0.0]])
    out = np.empty(2)
    assert _selection.masked_medians(vectors, np.array([1, 1, 0, 1], dtype=bool), out) == 3
    np.testing.assert_array_equal(out, [2.0, 5.0])
    assert _selection.masked_medians(vectors, np.zeros(4, dtype=bool), out) == 0
    assert np.isnan(out).all()


@pytest.mark.parametrize("mad", [True, False])
def test_select_blocks_is_usable_then_outlier_rule_then_mean_std(mad: bool) -> None:
    """The one-call selection of combine against its three steps."""
    from afmdrift.registration._outliers import MAD_FLOOR_PX, MAX_ITER

    vectors = np.vstack([RNG.normal([3.0, -2.0], 0.05, size=(40, 2)), [[9.0, 4.0], [3.4, -2.0]]])
    measured = RNG.random(42) < 0.9
    placed = RNG.random(42) < 0.8
    in_overlap = np.ones(42, dtype=bool)
    usable, valid = np.empty((2, 42), dtype=bool)
    stats = np.empty(4)
    rule = _selection.MadRule(threshold=3.5, floor=MAD_FLOOR_PX, max_iter=MAX_ITER)
    available, n_valid = _selection.select_blocks(
        vectors, measured, placed, in_overlap,
        _selection.SelectionRule(min_blocks=8, mad=mad, mad_rule=rule, epsilon=0.5),
        usable, valid, stats,
    )  # fmt: skip
    np.testing.assert_array_equal(usable, measured & placed)
    assert available == placed.sum()
    expect = np.empty(42, dtype=bool)
    if mad:
        _selection.reject_mad(vectors, usable, rule, expect)
    else:
        _selection.reject_paper(vectors, usable, 0.5, expect)
    np.testing.assert_array_equal(valid, expect)
    assert n_valid == expect.sum() > 20
    assert not valid[40]
    np.testing.assert_allclose(stats[:2], vectors[expect].mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(stats[2:], vectors[expect].std(axis=0, ddof=1), rtol=1e-12)


@pytest.mark.parametrize("size", [8, 32])
@pytest.mark.parametrize("n", [1, 9, 16, 20, 36, 64, 80, 100])
def test_batch_split_covers_every_block_once_with_smaller_last_batches(n: int, size: int) -> None:
    from afmdrift.registration._passes import batch_split

    batches = batch_split(n, size)
    assert [b.start for b in batches] == [0, *(b.stop for b in batches[:-1])]
    assert batches[-1].stop == n
    sizes = [b.stop - b.start for b in batches]
    assert max(sizes) <= size
    assert sizes == sorted(sizes, reverse=True)
    # The last 2 * size blocks, and what does not fill a whole batch
    # before them, are in half batches.
    small = sum(s for s in sizes if s < size)
    assert min(n, 2 * size) <= small < 3 * size
    if n >= 2 * size:
        assert sizes[-1] <= size // 2


def test_smaller_windows_go_in_larger_batches() -> None:
    from afmdrift.registration._passes import BATCH_BLOCKS, batch_blocks

    assert batch_blocks((128, 128)) == BATCH_BLOCKS
    assert batch_blocks((64, 64)) == 4 * BATCH_BLOCKS
    assert batch_blocks((256, 256)) == BATCH_BLOCKS


def test_every_kernel_cache_is_stamped_with_all_kernel_modules() -> None:
    """Regression guard: Numba stamps a cached kernel with its own module's
    source only (numba#1833), so a kernel inlining one of another module kept
    the old code after that module changed. Every compiled kernel of the
    package lives in a module of ``KERNEL_MODULES`` and its cache carries the
    digest of all of them."""
    import importlib
    import pkgutil

    from numba.core.dispatcher import Dispatcher

    import afmdrift.registration as registration
    from afmdrift.registration import _jit

    found = set()
    for info in pkgutil.iter_modules(registration.__path__):
        module = importlib.import_module(f"afmdrift.registration.{info.name}")
        for obj in vars(module).values():
            if isinstance(obj, Dispatcher) and obj.py_func.__module__ == module.__name__:
                found.add(info.name)
                stamp = obj._cache._cache_file._source_stamp
                assert stamp[1] == _jit._SOURCES, obj
    assert found == set(_jit.KERNEL_MODULES) - {"_jit"}  # _jit only compiles them

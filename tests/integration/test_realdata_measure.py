"""Drift measurement on the real AFM files: consistency checks (no ground truth exists).

What the files show (``shared/data/real/README.md``):

* NanoScope pair: a lattice (period about 10 px) moved by about 28 px along y
  (rows) between the two images, says the README: the highest peak of their
  phase correlation. The content does not say which lattice translation it
  is (issue 29): blocks placed at (0.3, 28.3), (2.2, 18.0), (−7.5, 21.5) or
  (9.9, 24.8) px each give a valid result with σ of 0.035 px, and the
  frames' residuals differ by no more than noise between them. So the pair
  is refused without an expected drift and measured with one. We build the
  truth ourselves by Fourier shifting the real ``.002`` texture.
* HS-AFM movie: sub-pixel drift per frame; frames decorrelate from about
  frame 16 on (line artefacts, the coarse correlation peak falls below its
  significance cut-off) and frame 28 is blank.

Measurements run exactly as ``afmdrift measure`` runs them (coarse
pre-alignment, ±6 px block search), with 32/64 px blocks for these small
images (``--block-size 32 --extended-size 64``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import fourier_shift

from afmdrift.cli import main
from afmdrift.cli._measure import measure_pair
from afmdrift.cli._measure import measurement_config as _config
from afmdrift.io import AfmImage, load_image, load_stack
from afmdrift.registration import (
    DriftTracker,
    InvalidFrameError,
    RegistrationConfig,
    coarse_shift,
    measure_drift,
)
from afmdrift.runs import track_stack

pytestmark = pytest.mark.realdata

RealFile = Callable[[str], Path]
SMALL = _config(RegistrationConfig(), block_size=32, extended_size=64)
#: Heights instead of the x gradient: better on the quantised HS-AFM movie (see below).
HSAFM = _config(RegistrationConfig(gradient="none"), block_size=32, extended_size=64)
#: Agreement required between a direct and a chained measurement (brief: 0.3 px).
CLOSURE_PX = 0.3
#: Border removed after Fourier shifting, so the periodic wrap-around never enters.
CROP = 24


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """A feature at u appears at u + (dx, dy)."""
    return np.fft.ifft2(fourier_shift(np.fft.fft2(img), (dy, dx))).real


def _image(heights: np.ndarray, like: AfmImage, name: str) -> AfmImage:
    return AfmImage(heights_nm=heights, pixel_size_nm=like.pixel_size_nm, path=Path(name))


def _crop(img: np.ndarray) -> np.ndarray:
    return img[CROP:-CROP, CROP:-CROP]


@pytest.fixture(scope="module")
def nanoscope(real_data_dir: Path) -> tuple[AfmImage, AfmImage]:
    paths = [real_data_dir / f"nanoscope3a_15um.00{i}" for i in (2, 4)]
    if not all(p.is_file() for p in paths):
        pytest.skip(f"NanoScope files not found in {real_data_dir}")
    return load_image(paths[0]), load_image(paths[1])


@pytest.fixture(scope="module")
def real_data_dir() -> Path:
    """Module-scoped twin of the conftest fixture, so files load once per module."""
    path = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
    if not path.is_dir():
        pytest.skip(f"real AFM data folder not found at {path}")
    return path


@pytest.mark.parametrize("config", [RegistrationConfig(), SMALL], ids=["64-128", "32-64"])
@pytest.mark.parametrize("shift", [(0.37, -0.61), (2.3, 1.45), (-0.25, 14.3)])
def test_known_subpixel_shift_of_real_texture_is_recovered(
    nanoscope: tuple[AfmImage, AfmImage],
    config: RegistrationConfig,
    shift: tuple[float, float],
) -> None:
    ref, _ = nanoscope
    moved = _shifted(ref.heights_nm, *shift)
    pair = measure_pair(
        _image(_crop(ref.heights_nm), ref, "ref"),
        _image(_crop(moved), ref, "moved"),
        _config(config),
    )
    assert pair.valid
    assert pair.dx_px == pytest.approx(shift[0], abs=0.05)
    assert pair.dy_px == pytest.approx(shift[1], abs=0.05)


#: The README's shift of the pair and the other lattice translations of it that
#: fit as well (blocks placed at each: valid, σ about 0.035 px).
NANOSCOPE_PAIR_PX = (0.3, 28.3)
NANOSCOPE_TRANSLATIONS_PX = ((2.2, 18.0), (-7.5, 21.5), (9.9, 24.8))


def _names(
    shifts: list[list[float]] | tuple[tuple[float, float], ...], d: tuple[float, float]
) -> bool:
    return any(abs(a - d[0]) < 1.0 and abs(b - d[1]) < 1.0 for a, b in shifts)


@pytest.mark.parametrize("config", [RegistrationConfig(), SMALL], ids=["64-128", "32-64"])
def test_nanoscope_direct_equals_chain_through_synthetic_intermediate(
    nanoscope: tuple[AfmImage, AfmImage], config: RegistrationConfig
) -> None:
    """0 = .002, 1 = .002 moved partway by a known sub-pixel shift, 2 = .004:
    measuring 0→2 directly must agree with 0→1 + 1→2. The lattice translation
    of 1→2 and 0→2 is the content's to decide, which it cannot (module
    docstring): both are refused without an expected drift, naming the
    README's translation, and measured with it."""
    a, b = nanoscope
    mid = _shifted(a.heights_nm, -0.25, 14.3)
    im0, im1, im2 = (
        _image(_crop(h), a, n) for h, n in ((a.heights_nm, "0"), (mid, "1"), (b.heights_nm, "2"))
    )
    cfg = _config(config)
    r01 = measure_pair(im0, im1, cfg)
    assert r01.valid, r01.reason  # the same texture: the content decides
    assert (r01.dx_px, r01.dy_px) == pytest.approx((-0.25, 14.3), abs=0.05)
    expect02 = NANOSCOPE_PAIR_PX
    expect12 = (expect02[0] + 0.25, expect02[1] - 14.3)
    for ref, cur, expect in ((im1, im2, expect12), (im0, im2, expect02)):
        blind = measure_pair(ref, cur, cfg)
        assert not blind.valid
        assert blind.reason is not None
        assert blind.reason.startswith("ambiguous"), blind.reason
        assert _names(blind.lattice_px, expect), blind.lattice_px
    r12 = measure_pair(im1, im2, cfg, prior_px=(round(expect12[0]), round(expect12[1])))
    r02 = measure_pair(im0, im2, cfg, prior_px=(round(expect02[0]), round(expect02[1])))
    assert r12.valid, r12.reason
    assert r02.valid, r02.reason
    assert r01.dx_px + r12.dx_px == pytest.approx(r02.dx_px, abs=CLOSURE_PX)
    assert r01.dy_px + r12.dy_px == pytest.approx(r02.dy_px, abs=CLOSURE_PX)


def test_nanoscope_pair_cli(real_file: RealFile, capsys: pytest.CaptureFixture[str]) -> None:
    """Without an expected drift the pair is refused (exit status 1) as
    ambiguous, the README's shift and (2.2, 18.0) among the lattice
    translations named; with
    ``--prior-px 0 28`` it is about 28 px along y and x within a pixel of
    zero, decided by the prior alone (exit status 3, the alternatives named)."""
    a, b = real_file("nanoscope3a_15um.002"), real_file("nanoscope3a_15um.004")
    assert main(["measure", str(a), str(b), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["valid"] is False
    assert doc["reason"].startswith("ambiguous")
    for d in (NANOSCOPE_PAIR_PX, NANOSCOPE_TRANSLATIONS_PX[0]):
        assert _names(doc["lattice_px"], d), (d, doc["lattice_px"])
    assert main(["measure", str(a), str(b), "--json", "--prior-px", "0", "28"]) == 3
    doc = json.loads(capsys.readouterr().out)
    assert doc["prior_px"] == [0.0, 28.0]
    assert doc["given_prior_px"] == [0.0, 28.0]
    assert doc["decided_by"] == "prior"
    assert doc["ambiguity_px"] == pytest.approx(10.1, abs=0.5)
    assert doc["dy_px"] == pytest.approx(28.0, abs=1.0)
    assert doc["dx_px"] == pytest.approx(0.0, abs=1.0)
    assert doc["dy_nm"] == pytest.approx(doc["dy_px"] * 15000 / 256)
    assert doc["sigma_nm"] < 30.0  # half a pixel


@pytest.mark.parametrize("config", [RegistrationConfig(), SMALL], ids=["64-128", "32-64"])
def test_nanoscope_pair_is_ambiguous_and_each_translation_fits(
    nanoscope: tuple[AfmImage, AfmImage], config: RegistrationConfig
) -> None:
    """Regression (issue 29): the coarse alignment took the highest phase
    correlation peak, (0, 28), which the frames' edges favour (their columns
    line up at a whole-pixel x shift); the content fits the lattice
    translations (2.2, 18.0), (−7.5, 21.5) and (9.9, 24.8) px as well, and
    blocks placed at each agree on it. Without an expected drift the coarse
    alignment is ambiguous and names the tied translations near zero, among
    them the README's and (2.2, 18.0), and neither measure_drift nor a
    DriftTracker (the service's path) gives a number; with one, the
    translation nearest it is measured."""
    a, b = nanoscope
    assert a.pixel_size_nm == pytest.approx((58.59, 58.59), abs=0.01)
    c = coarse_shift(a.heights_nm, b.heights_nm)
    assert c.ambiguous
    assert not c.trusted
    for d in (NANOSCOPE_PAIR_PX, NANOSCOPE_TRANSLATIONS_PX[0]):
        assert _names(c.candidates_px, d), (d, c.candidates_px)
    r = measure_drift(a.heights_nm, b.heights_nm, pixel_size_nm=a.pixel_size_nm, config=config)
    assert not r.valid
    assert r.reason is not None
    assert r.reason.startswith("ambiguous")
    tracker = DriftTracker(pixel_size_nm=a.pixel_size_nm, config=config)
    tracker.update(a.heights_nm)
    step = tracker.update(b.heights_nm)
    assert step is not None
    assert not step.accepted
    assert step.position_px == (0.0, 0.0)
    for d in (NANOSCOPE_PAIR_PX, *NANOSCOPE_TRANSLATIONS_PX):
        r = measure_drift(
            a.heights_nm, b.heights_nm, pixel_size_nm=a.pixel_size_nm, config=config, prior_px=d
        )
        assert r.valid, (d, r.reason)
        assert (r.dx_px, r.dy_px) == pytest.approx(d, abs=0.5)
        assert r.sigma_nm / a.pixel_size_nm[0] < 0.1


# --------------------------------------------------------------------------- HS-AFM movie


@pytest.fixture(scope="module")
def movie(real_data_dir: Path) -> list[AfmImage]:
    path = real_data_dir / "hsafm_sample_0.asd"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    return load_stack(path)


def _closures(
    movie: list[AfmImage], last: int, config: RegistrationConfig
) -> list[tuple[int, float, float, float, float]]:
    """(j, error_x_px, error_y_px, sigma_x_px, sigma_y_px) of direct 0→j minus the chained
    consecutive track, for every j <= last where both are valid and frame j still
    correlates with frame 0 (coarse peak above its cut-off). Sigmas combine the
    engine's reported uncertainties of all measurements involved."""
    chain: dict[int, tuple[float, float, float, float]] = {}
    var = np.zeros(2)
    for d in track_stack(movie[: last + 1], config):
        if d["valid"]:
            px, py = movie[0].pixel_size_nm
            var += np.array([d["sigma_x_nm"] / px, d["sigma_y_nm"] / py]) ** 2
            chain[d["cur_frame"]] = (d["cumulative_dx_px"], d["cumulative_dy_px"], *var)
    out = []
    for j in range(2, last + 1):
        if j not in chain:
            continue
        if not coarse_shift(movie[0].heights_nm, movie[j].heights_nm).trusted:
            continue
        r = measure_pair(movie[0], movie[j], config)
        if not r.valid:
            continue
        px, py = movie[0].pixel_size_nm
        cx, cy, vx, vy = chain[j]
        sx = float(np.sqrt(vx + (r.sigma_x_nm / px) ** 2))
        sy = float(np.sqrt(vy + (r.sigma_y_nm / py) ** 2))
        out.append((j, r.dx_px - cx, r.dy_px - cy, sx, sy))
    return out


@pytest.mark.slow
def test_hsafm_direct_equals_sum_of_consecutive(movie: list[AfmImage]) -> None:
    """Frame 0→j measured directly agrees with the sum of the consecutive
    measurements within 0.3 px, for every j up to 21 where both are valid and
    frame j still correlates with frame 0 (coarse alignment trusted: frames
    2–13; later frames decorrelate, are line artefacts or blank).

    This holds with heights (``gradient = "none"``) and 32/64 px blocks:
    closures 0.06–0.27 px, 37–44 of 49 blocks valid. With the default x
    gradient it does not (0.14–0.52 px over frames 2–13, growing with j, 23–37
    valid blocks): the movie's heights are quantised to about 30 levels, and
    differentiating them whitens and doubles that quantisation noise, which
    these smooth, small (200 px) frames cannot average away; each x-gradient
    step carries 0.15–0.2 px of noise and the chain random-walks. Line
    offsets, which the x gradient exists to cancel, are small in this movie."""
    checked = _closures(movie, last=21, config=HSAFM)
    assert len(checked) >= 10, f"too few comparable frames: {[c[0] for c in checked]}"
    for j, ex, ey, _sx, _sy in checked:
        assert abs(ex) <= CLOSURE_PX, f"frame {j}: x {ex:+.3f} px"
        assert abs(ey) <= CLOSURE_PX, f"frame {j}: y {ey:+.3f} px"


@pytest.mark.slow
def test_hsafm_x_gradient_closures_stay_within_their_uncertainty(movie: list[AfmImage]) -> None:
    """With the default x gradient the closures exceed 0.3 px (see above) but
    stay within 0.3 px plus three combined standard uncertainties: the
    engine's sigma accounts for the extra quantisation noise."""
    checked = _closures(movie, last=21, config=SMALL)
    assert len(checked) >= 10, f"too few comparable frames: {[c[0] for c in checked]}"
    for j, ex, ey, sx, sy in checked:
        assert abs(ex) <= CLOSURE_PX + 3 * sx, f"frame {j}: x {ex:+.3f} px, sigma {sx:.3f}"
        assert abs(ey) <= CLOSURE_PX + 3 * sy, f"frame {j}: y {ey:+.3f} px, sigma {sy:.3f}"


def test_hsafm_blank_frame_is_an_error_not_a_number(
    movie: list[AfmImage], real_file: RealFile, capsys: pytest.CaptureFixture[str]
) -> None:
    """Frame 28 is blank: measuring against it must refuse, never return a drift.
    (Frame 27, nearly blank, is refused first when it is the reference.)"""
    with pytest.raises(InvalidFrameError, match="constant"):
        measure_pair(movie[0], movie[28], SMALL)
    with pytest.raises(InvalidFrameError, match="reference is nearly blank"):
        measure_pair(movie[27], movie[28], SMALL)
    path = real_file("hsafm_sample_0.asd")
    assert main(["measure", f"{path}:0", f"{path}:28"]) == 2
    err = capsys.readouterr().err
    assert "constant" in err
    assert "Traceback" not in err
    # the blank frame between two good ones (timestamps dropped: a stack is
    # tracked in time order, and this order is not the movie's)
    frames = [dataclasses.replace(movie[k], timestamp=None) for k in (0, 1, 28, 2)]
    docs = list(track_stack(frames, SMALL))
    assert [(d["ref_frame"], d["cur_frame"]) for d in docs] == [(0, 1), (0, 2), (0, 3)]
    assert docs[1]["valid"] is False
    assert "constant" in docs[1]["error"]
    assert "dx_px" not in docs[1]
    assert docs[2]["valid"] is True  # the track continues past the blank frame


@pytest.mark.parametrize("config", [RegistrationConfig(), SMALL], ids=["64-128", "32-64"])
@pytest.mark.parametrize("pair", [(21, 22), (22, 23), (0, 23), (26, 27), (0, 27), (27, 29)])
def test_hsafm_near_blank_frames_are_refused_or_invalid_without_warnings(
    movie: list[AfmImage], config: RegistrationConfig, pair: tuple[int, int]
) -> None:
    """Regression: near-blank frames 22, 23 and 27 (flat windows: block
    spectra exactly zero) made the engine's reciprocal overflow (numpy
    RuntimeWarnings, errors in this suite), and frame 27 (0.18 % non-zero
    gradient) once gave a confident (−19.5, 11.2) px from four agreeing
    blocks. Frame 27 is refused with a typed error; pairs with 22 or 23
    come out invalid with a reason."""
    a, b = pair
    ref, cur = movie[a].heights_nm, movie[b].heights_nm
    if 27 in pair:
        with pytest.raises(InvalidFrameError, match="nearly blank"):
            measure_drift(ref, cur, pixel_size_nm=0.5, config=config)
        return
    r = measure_drift(ref, cur, pixel_size_nm=0.5, config=config)
    assert not r.valid
    assert r.reason


@pytest.mark.slow
def test_hsafm_movie_cli_reports_no_wrong_numbers_on_bad_frames(
    real_file: RealFile, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression: frames 22–31 are scan-line streaks and a blank frame. Their
    levelled heights correlate strongly at spurious shifts (30–90 px); used as
    a prior, that gave confident wrong drifts. Every valid increment of this
    movie must be a few px at most, and the streak frames must come out invalid
    (without numpy warnings, which this suite turns into errors)."""
    path = real_file("hsafm_sample_0.asd")
    code = main(["measure", str(path), "--block-size", "32", "--extended-size", "64"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert code == 1
    assert len(lines) == 31
    for d in lines:
        if d["valid"]:
            assert np.hypot(d["dx_px"], d["dy_px"]) < 3.0, d
    assert not any(d["valid"] for d in lines if d["cur_frame"] >= 22)
    assert sum(d["valid"] for d in lines if d["cur_frame"] <= 16) >= 14  # good frames measure
    assert [d["cur_t_s"] for d in lines] == [float(j) for j in range(1, 32)]  # 1 s/frame
    blank = next(d for d in lines if d["cur_frame"] == 28)
    assert "constant" in blank["error"]

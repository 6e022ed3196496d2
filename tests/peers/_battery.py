"""Peer test battery of issue 13: other registration projects' translation cases.

Each :class:`Case` re-creates, in our own code, the facts of one test from
another project (image type and size, the shift, noise, mask, the peer's
tolerance) and says where it comes from. Where the peer's image ships with
a data package we do not have, an equivalent texture stands in (said in the
case's ``note``). The tests in ``tests/peers/test_peers.py`` and
``benchmarks/peer_battery.py`` both run the cases defined here (one path).

Verdicts (:func:`run_case`):

- **pass**: a valid result within the peer's tolerance *and* within
  ``max(0.5 px, 4σ)`` of the truth on each axis (σ in px per axis is
  ``sigma_x_nm / pixel_size_x_nm``).
- **refused**: ``valid`` False, or a typed :class:`~afmdrift.errors.InputError`;
  the reason is kept. A refusal where the peer meets its own assertion
  (``peer_succeeds``) is a *needless* refusal.
- **short**: a valid result within ``max(0.5 px, 4σ)`` (its uncertainty is
  honest) that misses the peer's tighter tolerance.
- **fail**: a valid result whose error exceeds ``max(0.5 px, 4σ)`` on an
  axis: a confident wrong answer, the worst outcome.

Sign convention (afmdrift): a feature at ``u`` in the reference appears at
``u + d`` in the current frame, x along columns, y along rows. The peers'
conventions differ (scikit-image returns the shift that registers the moving
image, the opposite sign); each case states its truth in ours.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.errors import InputError
from afmdrift.registration import DriftTracker, RegistrationConfig, measure_drift
from afmdrift.testing import (
    DISTORTIONS,
    Particles,
    TextureShifter,
    add_noise,
    band_limit,
    distorted_crop,
    fourier_shift,
    particle_texture,
    rough_texture,
    terrace_texture,
)

FloatArray = npt.NDArray[np.float64]

#: ``../shared/data/real`` next to the repository (read in place, never copied).
REAL_DATA_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"

NANOSCOPE = "nanoscope3a_15um.002"
HSAFM = "hsafm_sample_0.asd"


class MissingDataError(Exception):
    """A real-data file of a case is absent (tests skip, the benchmark says so)."""


def real_path(name: str) -> Path:
    p = REAL_DATA_DIR / name
    if not p.is_file():
        raise MissingDataError(f"real AFM file {name} not found in {REAL_DATA_DIR.resolve()}")
    return p


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class Pair:
    """Two frames and the true drift ``(dx, dy)`` px of ``current`` against ``reference``."""

    reference: FloatArray
    current: FloatArray
    truth: tuple[float, float] | None
    pixel_size_nm: float = 1.0
    config: RegistrationConfig | None = None
    #: Truth unknown: a valid result must lie within this many px of zero.
    bound_px: float | None = None
    #: The expected drift given to ``measure_drift`` (None: the coarse alignment).
    prior_px: tuple[float, float] | None = None
    #: Period (px, both axes) of a perfect lattice whose translations register
    #: the frames equally well: a result a whole number of periods from the
    #: truth is right (the peer asserts registered frames, and afmdrift is
    #: asked for them, ``lattice = "equivalent"``).
    equivalent_period_px: float | None = None


@dataclass(frozen=True)
class Stack:
    """Frames for a :class:`DriftTracker` and the true cumulative positions (px)."""

    frames: list[FloatArray]
    positions: list[tuple[float, float]] | None  # None: truth unknown
    pixel_size_nm: float = 1.0
    config: RegistrationConfig | None = None
    #: Truth unknown: every accepted increment must be within this many px of zero.
    bound_step_px: float | None = None


@dataclass(frozen=True)
class Case:
    """One peer test re-created for afmdrift."""

    peer: str
    name: str
    source: str  # repository and path of the peer's test
    asserts: str  # what the peer asserts, in words
    tol_px: float  # the peer's tolerance (per axis, or on the norm if tol_norm)
    build: Callable[[], Pair | Stack] = field(repr=False)
    tol_norm: bool = False
    note: str = ""  # how our re-creation differs from the peer's test
    peer_succeeds: bool = True  # the peer meets its own assertion on this case
    realdata: bool = False
    slow: bool = False
    #: Set while afmdrift refuses a case the peer solves (issue 13 is fixing it):
    #: the peer-tolerance test is then marked xfail(strict=True) with this reason.
    known_refusal: str | None = None

    @property
    def id(self) -> str:
        return f"{self.peer}:{self.name}"


VERDICTS: tuple[str, ...] = ("pass", "refused", "short", "fail", "skipped")


@dataclass(frozen=True)
class Outcome:
    """afmdrift's answer on one case and its verdict."""

    case: Case
    verdict: str  # pass / refused / short / fail / skipped
    result_px: tuple[float, float] | None = None
    error_px: tuple[float, float] | None = None
    sigma_px: tuple[float, float] | None = None
    reason: str | None = None
    detail: str = ""  # per-frame detail of stack cases, skip reason

    @property
    def needless(self) -> bool:
        """A refusal where the peer meets its own assertion."""
        return self.verdict == "refused" and self.case.peer_succeeds


# --------------------------------------------------------------------------- verdicts


def _bound(sigma: float) -> float:
    return max(0.5, 4.0 * sigma) if math.isfinite(sigma) else math.inf


def _within_peer(case: Case, err: tuple[float, float]) -> bool:
    if case.tol_norm:
        return math.hypot(*err) <= case.tol_px
    return max(err) <= case.tol_px


def _judge(
    case: Case,
    got: tuple[float, float],
    truth: tuple[float, float],
    sigma: tuple[float, float],
    period: float | None = None,
) -> tuple[str, tuple[float, float]]:
    diff = (got[0] - truth[0], got[1] - truth[1])
    if period is not None:
        # lattice-equivalent: a whole number of periods off registers alike
        diff = (
            diff[0] - period * round(diff[0] / period),
            diff[1] - period * round(diff[1] / period),
        )
    err = (abs(diff[0]), abs(diff[1]))
    if not (err[0] <= _bound(sigma[0]) and err[1] <= _bound(sigma[1])):
        return "fail", err
    return ("pass" if _within_peer(case, err) else "short"), err


def _run_pair(case: Case, pair: Pair) -> Outcome:
    try:
        r = measure_drift(
            pair.reference,
            pair.current,
            pixel_size_nm=pair.pixel_size_nm,
            config=pair.config,
            prior_px=pair.prior_px,
        )
    except InputError as err:
        return Outcome(case, "refused", reason=f"{type(err).__name__}: {err}")
    return judge_pair(
        case,
        pair,
        valid=r.valid,
        got=(float(r.dx_px), float(r.dy_px)),
        sigma_nm=(r.sigma_x_nm, r.sigma_y_nm),
        reason=r.reason,
    )


def judge_pair(
    case: Case,
    pair: Pair,
    *,
    valid: bool,
    got: tuple[float, float],
    sigma_nm: tuple[float, float],
    reason: str | None,
) -> Outcome:
    """Verdict on one measured pair (also used for the CLI's JSON answer)."""
    if not valid:
        return Outcome(case, "refused", reason=reason or "(no reason given)")
    sigma = (sigma_nm[0] / pair.pixel_size_nm, sigma_nm[1] / pair.pixel_size_nm)
    if pair.truth is None:
        # Truth unknown: only a bound on the drift is known.
        bound = pair.bound_px if pair.bound_px is not None else math.inf
        ok = math.hypot(*got) <= bound
        return Outcome(
            case,
            "pass" if ok else "fail",
            got,
            None,
            sigma,
            detail=f"truth unknown; |d| must be <= {bound:g} px",
        )
    verdict, err = _judge(case, got, pair.truth, sigma, pair.equivalent_period_px)
    return Outcome(case, verdict, got, err, sigma)


def _run_stack(case: Case, stack: Stack) -> Outcome:
    tracker = DriftTracker(pixel_size_nm=stack.pixel_size_nm, config=stack.config)
    tracker.update(stack.frames[0])
    var = np.zeros(2)
    worst: tuple[str, tuple[float, float], tuple[float, float], tuple[float, float]] | None = None
    refusals: list[str] = []
    bad: list[str] = []  # accepted increments beyond the bound (truth unknown)
    rank = {"pass": 0, "short": 1, "fail": 2}
    for j in range(1, len(stack.frames)):
        try:
            step = tracker.update(stack.frames[j])
        except InputError as err:
            refusals.append(f"frame {j}: {type(err).__name__}: {err}")
            continue
        assert step is not None
        if not step.accepted:
            refusals.append(f"frame {j}: {step.measurement.reason}")
            continue
        inc = step.increment
        inc_sigma = (inc.sigma_x_nm / stack.pixel_size_nm, inc.sigma_y_nm / stack.pixel_size_nm)
        if stack.positions is None:
            # Truth unknown: judge each accepted increment against the bound.
            got = (float(inc.dx_px), float(inc.dy_px))
            bound = stack.bound_step_px if stack.bound_step_px is not None else math.inf
            verdict = "pass" if math.hypot(*got) <= bound else "fail"
            if verdict == "fail":
                bad.append(f"frame {j}: ({got[0]:.2f}, {got[1]:.2f})")
            cand = (verdict, got, (math.nan, math.nan), inc_sigma)
            if worst is None or (rank[verdict], math.hypot(*got)) > (
                rank[worst[0]],
                math.hypot(*worst[1]),
            ):
                worst = (*cand[:2], cand[2], cand[3])
                worst_frame = j
            continue
        var += np.array(inc_sigma) ** 2
        sigma = (float(np.sqrt(var[0])), float(np.sqrt(var[1])))
        got = (float(step.position_px[0]), float(step.position_px[1]))
        verdict, err = _judge(case, got, stack.positions[j], sigma)
        if worst is None or (rank[verdict], max(err)) > (rank[worst[0]], max(worst[2])):
            worst = (verdict, got, err, sigma)
            worst_frame = j
    refused = "; ".join(refusals) if refusals else None
    if worst is not None and worst[0] == "fail":
        err_out = None if stack.positions is None else worst[2]
        what = "increment" if stack.positions is None else "position"
        return Outcome(
            case,
            "fail",
            worst[1],
            err_out,
            worst[3],
            reason=refused,
            detail=(
                "accepted increments beyond the bound: " + ", ".join(bad)
                if bad
                else f"frame {worst_frame}: accepted {what} {worst[1]}"
            ),
        )
    if refused is not None and (stack.positions is not None or worst is None):
        return Outcome(case, "refused", reason=refused)
    assert worst is not None
    err_out = None if stack.positions is None else worst[2]
    return Outcome(
        case, worst[0], worst[1], err_out, worst[3], reason=refused, detail="worst frame"
    )


def run_case(case: Case) -> Outcome:
    """Build the case's frames, measure them, and judge the answer."""
    try:
        data = case.build()
    except MissingDataError as err:
        return Outcome(case, "skipped", detail=str(err))
    if isinstance(data, Stack):
        return _run_stack(case, data)
    return _run_pair(case, data)


@functools.cache
def outcome(case_id: str) -> Outcome:
    """:func:`run_case` once per process (both tests of a case share it)."""
    return run_case(CASES_BY_ID[case_id])


# --------------------------------------------------------------------------- images


def _gray(rgb: npt.NDArray[np.generic]) -> FloatArray:
    a = np.asarray(rgb, dtype=np.float64)
    return a if a.ndim == 2 else a[..., :3] @ np.array([0.2125, 0.7154, 0.0721])


@functools.cache
def _skdata(name: str) -> FloatArray:
    """A grey-level image that ships with scikit-image (no download)."""
    import skimage.data

    img = _gray(getattr(skimage.data, name)())
    img.setflags(write=False)
    return img


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


# --------------------------------------------------------------------------- scikit-image

SK_PCC = "scikit-image/scikit-image skimage/registration/tests/test_phase_cross_correlation.py"
SK_MASKED = (
    "scikit-image/scikit-image skimage/registration/tests/test_masked_phase_cross_correlation.py"
)


def _sk_fourier(dx: float, dy: float, dtype: type = np.float64) -> Callable[[], Pair]:
    def build() -> Pair:
        ref = _skdata("camera").astype(dtype)
        cur = fourier_shift(ref.astype(np.float64), dx_px=dx, dy_px=dy).astype(dtype)
        return Pair(ref.astype(np.float64), cur.astype(np.float64), (dx, dy))

    return build


@functools.cache
def _disambiguation_texture() -> FloatArray:
    # A highly textured 800² stand-in for the crop of skimage.data.eagle().
    tex = rough_texture((800, 800), pixel_size_nm=1.0, rng=_rng(1301), correlation_length_nm=1.5)
    tex.setflags(write=False)
    return tex


def _sk_disambiguate(s0: int, s1: int) -> Callable[[], Pair]:
    def build() -> Pair:
        img = _disambiguation_texture()
        o0 = [0 if s > 0 else -s for s in (s0, s1)]
        o1 = [o + s for o, s in zip(o0, (s0, s1), strict=True)]
        ref = img[o0[0] : o0[0] + 450, o0[1] : o0[1] + 450]
        cur = img[o1[0] : o1[0] + 450, o1[1] : o1[1] + 450]
        # skimage's answer (s0, s1) registers `cur` onto `ref`: the content moved by -s.
        return Pair(ref.copy(), cur.copy(), (float(-s1), float(-s0)))

    return build


@functools.cache
def _afm_disambiguation_texture(kind: str) -> FloatArray:
    # AFM-like 800² textures for the same crops: particles on a flat substrate
    # and graphite-like terraces (smooth, with steps), 2 nm/px.
    rng = _rng(2901)
    if kind == "particles":
        tex = particle_texture((800, 800), pixel_size_nm=2.0, rng=rng)
    else:
        tex = terrace_texture((800, 800), pixel_size_nm=2.0, rng=_rng(2902))
    tex.setflags(write=False)
    return tex


def _sk_disambiguate_afm(kind: str, s0: int, s1: int) -> Callable[[], Pair]:
    def build() -> Pair:
        img = _afm_disambiguation_texture(kind)
        o0 = [0 if s > 0 else -s for s in (s0, s1)]
        o1 = [o + s for o, s in zip(o0, (s0, s1), strict=True)]
        ref = img[o0[0] : o0[0] + 450, o0[1] : o0[1] + 450]
        cur = img[o1[0] : o1[0] + 450, o1[1] : o1[1] + 450]
        return Pair(ref.copy(), cur.copy(), (float(-s1), float(-s0)), 2.0)

    return build


def _sk_masked_random() -> Pair:
    rng = _rng(23)
    ref = _skdata("camera").copy()
    cur = fourier_shift(ref, dx_px=12.0, dy_px=-7.0)
    # 75 % valid pixels in each frame, independently. afmdrift takes no mask:
    # invalid pixels are set to the frame's mean (impulsive, non-moving noise).
    for img in (ref, cur):
        bad = rng.random(img.shape) >= 0.75
        img[bad] = img.mean()
    return Pair(ref, cur, (12.0, -7.0))


def _sk_padfield(dx: int, dy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        img = _skdata("astronaut")
        n, border = 320, 24
        bx, by = (130 if dx > 0 else 40), 130
        ref = img[by : by + n, bx : bx + n].copy()
        # Content moves by (dx, dy): the current frame shows the scene at -d.
        cur = img[by - dy : by - dy + n, bx - dx : bx - dx + n].copy()
        # The invalid region (zero in both frames, at the same place) does not move.
        for a in (ref, cur):
            a[:border, :] = 0.0
            a[-border:, :] = 0.0
            a[:, :border] = 0.0
            a[:, -border:] = 0.0
        return Pair(ref, cur, (float(dx), float(dy)))

    return build


def _sk_padfield_disc(dx: int, dy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        pair = _sk_padfield(dx, dy)()
        n = pair.reference.shape[0]
        y, x = np.mgrid[:n, :n] - (n - 1) / 2.0
        outside = np.hypot(x, y) > 0.42 * n
        ref, cur = pair.reference.copy(), pair.current.copy()
        # A round field of view (as in Padfield's microscope images): the dark
        # outside, about 45 % of the frame, is the same in both frames.
        ref[outside] = 0.0
        cur[outside] = 0.0
        return Pair(ref, cur, pair.truth)

    return build


#: The AFM-like disambiguation pairs on which scikit-image 0.26's
#: phase_cross_correlation(disambiguate=True) misses the exact shift, by
#: 100 px (``benchmarks/peer_battery.py --reference``): the terraces moved by
#: 350 px both ways, whose 100² overlap is 5 % of the frame.
SK_AFM_DISAMBIGUATION_MISSED: frozenset[tuple[str, int, int]] = frozenset(
    ("terraces", s0, s1) for s0 in (350, -350) for s1 in (350, -350)
)

SKIMAGE: list[Case] = [
    Case(
        "skimage",
        "integer_shift",
        SK_PCC + " test_correlation",
        "camera 512², Fourier shift (rows, cols) = (−7, 12) recovered exactly",
        0.5,
        _sk_fourier(12.0, -7.0),
        note="exact integer asserted; our sub-pixel answer must round to it (≤ 0.5 px)",
    ),
    Case(
        "skimage",
        "subpixel_shift",
        SK_PCC + " test_subpixel_precision",
        "camera 512², Fourier shift (−2.4, 1.32), atol 0.05 px (upsample 100)",
        0.05,
        _sk_fourier(1.32, -2.4),
    ),
    Case(
        "skimage",
        "real_input_float32",
        SK_PCC + " test_real_input",
        "camera as float32, Fourier shift (−2.4, 1.32), atol 0.05 px",
        0.05,
        _sk_fourier(1.32, -2.4, np.float32),
    ),
    Case(
        "skimage",
        "real_input_float16",
        SK_PCC + " test_real_input",
        "camera as float16, Fourier shift (−2.4, 1.32), atol 0.05 px",
        0.05,
        _sk_fourier(1.32, -2.4, np.float16),
    ),
    Case(
        "skimage",
        "zero_shift",
        SK_PCC + " test_disambiguate_zero_shift",
        "camera against itself: exactly (0, 0)",
        0.5,
        _sk_fourier(0.0, 0.0),
    ),
    *[
        Case(
            "skimage",
            f"disambiguate_{s0:+d}_{s1:+d}",
            SK_PCC + " test_disambiguate_2d",
            f"450² crops {s0:+d}, {s1:+d} px apart (rows, cols), exact (disambiguate=True)",
            0.5,
            _sk_disambiguate(s0, s1),
            note="textured 800² rough surface (ℓ = 1.5 px) instead of skimage.data.eagle",
        )
        for s0 in (100, -100, 350, -350)
        for s1 in (100, -100, 350, -350)
    ],
    *[
        Case(
            "skimage",
            f"disambiguate_{kind}_{s0:+d}_{s1:+d}",
            SK_PCC + " test_disambiguate_2d",
            f"450² crops {s0:+d}, {s1:+d} px apart (rows, cols), exact (disambiguate=True)",
            0.5,
            _sk_disambiguate_afm(kind, s0, s1),
            note=f"AFM-like {kind} (800², 2 nm/px, noise-free) instead of skimage.data.eagle "
            "(issue 29); whether scikit-image 0.26 meets its assertion is from its answer on "
            "this pair (benchmarks/peer_battery.py --reference)",
            peer_succeeds=(kind, s0, s1) not in SK_AFM_DISAMBIGUATION_MISSED,
        )
        for kind in ("particles", "terraces")
        for s0 in (100, -100, 350, -350)
        for s1 in (100, -100, 350, -350)
    ],
    Case(
        "skimage",
        "masked_random_masks",
        SK_MASKED + " test_masked_registration_random_masks",
        "camera, shift (−7, 12), independent random masks (75 % valid): exact",
        0.5,
        _sk_masked_random,
        note="no mask input in afmdrift: invalid pixels set to the frame mean",
    ),
    *[
        Case(
            "skimage",
            f"masked_padfield_{dx:+d}_{dy:+d}",
            SK_MASKED + " test_masked_registration_padfield_data",
            f"Padfield's pair shifted ({dx:+d}, {dy:+d}) px, invalid (zero) region in "
            "both frames, masked: exact",
            0.5,
            _sk_padfield(dx, dy),
            note="astronaut 320² crops with a static 24-px zero border in both frames "
            "instead of Padfield's PNGs; no mask given to afmdrift",
        )
        for dx, dy in ((75, 75), (-130, 130), (130, 130))
    ],
    *[
        Case(
            "skimage",
            f"masked_round_view_{dx:+d}_{dy:+d}",
            SK_MASKED + " test_masked_registration_padfield_data",
            f"shift ({dx:+d}, {dy:+d}) px, a static invalid region in both frames, masked: exact",
            0.5,
            _sk_padfield_disc(dx, dy),
            note="astronaut 320² crops, round field of view (radius 0.42 n), the dark "
            "outside static in both frames; no mask given to afmdrift",
        )
        for dx, dy in ((75, 75), (130, 130))
    ],
]


# --------------------------------------------------------------------------- OpenCV

CV_PC = "opencv/opencv modules/imgproc/test/test_pc.cpp"


def _cv_rectangles() -> Pair:
    r1 = np.ones((128, 129))
    r2 = np.ones((128, 129))
    r1[100:111, 100:111] = 0.0  # an 11×11 filled square, x, y = 100…110
    r2[80:91, 90:101] = 0.0  # the same square at x = 90…100, y = 80…90
    return Pair(r1, r2, (-10.0, -20.0))


def _cv_real_129() -> Pair:
    img = _skdata("astronaut")
    roi1 = img[14 : 14 + 129, 40 : 40 + 129]
    roi2 = img[0:129, 0:129]
    # A scene point at p is at p − (40, 14) in roi1 and at p in roi2.
    return Pair(roi1.copy(), roi2.copy(), (40.0, 14.0))


def _cv_float32_large() -> Pair:
    from skimage.transform import resize

    im = _skdata("gravel") * (65535.0 / 255.0)
    w, h = im.shape[1] * 5, im.shape[0] * 5
    big = resize(im, (h, w), order=1, anti_aliasing=False).astype(np.float32)
    roi_w = (w * 2) // 3
    left, right = big[:, :roi_w], big[:, w - roi_w :]
    return Pair(left.astype(np.float64), right.astype(np.float64), (-float(w - roi_w), 0.0))


def _cv_rectangle_64(dx: int, dy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        r1, r2 = np.zeros((64, 64)), np.zeros((64, 64))
        top, left, h, w = 22, 20, 14, 20  # a bright 20×14 rectangle on a dark frame
        r1[top : top + h, left : left + w] = 1.0
        r2[top + dy : top + dy + h, left + dx : left + dx + w] = 1.0
        return Pair(r1, r2, (float(dx), float(dy)))

    return build


def _strands(shape: tuple[int, int], n: int, rng: np.random.Generator) -> FloatArray:
    """``n`` worm-like strands (DNA on mica): random walks of 120 px with 2-px
    wide Gaussian cross-sections, 1 nm high, periodic over the canvas."""
    rows, cols = shape
    y, x = np.mgrid[:rows, :cols]
    out = np.zeros(shape)
    for _ in range(n):
        px, py, angle = rng.uniform(0, cols), rng.uniform(0, rows), rng.uniform(0, 2 * math.pi)
        for _ in range(60):
            angle += rng.normal(0.0, 0.3)
            px, py = px + 2 * math.cos(angle), py + 2 * math.sin(angle)
            dx = (x - px + cols / 2) % cols - cols / 2
            dy = (y - py + rows / 2) % rows - rows / 2
            np.maximum(out, np.exp(-(dx**2 + dy**2) / (2 * 0.85**2)), out=out)
    return out


@functools.cache
def _smooth_few_features(k: int) -> FloatArray:
    # A JPK-like frame: a smooth background (correlation length 40–80 px) 10–100
    # times the height of a few sharp strands.
    rng = _rng(2910 + k)
    scale, ell, n = ((30.0, 60.0, 5), (100.0, 80.0, 5), (10.0, 40.0, 3), (30.0, 60.0, 2))[k]
    background = rough_texture(
        (320, 320), pixel_size_nm=1.0, rng=rng, rms_nm=scale, correlation_length_nm=ell
    )
    tex = background + band_limit(_strands((320, 320), n, rng))
    tex.setflags(write=False)
    return tex


def _cv_smooth(k: int, dx: int, dy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        tex = _smooth_few_features(k)
        m = 54  # content moves by (dx, dy): the current frame shows the texture at -d
        ref = tex[m : m + 212, m : m + 212]
        cur = tex[m - dy : m - dy + 212, m - dx : m - dx + 212]
        return Pair(ref.copy(), cur.copy(), (float(dx), float(dy)))

    return build


def _smooth_shifts() -> list[tuple[int, int, int]]:
    rng = _rng(2911)
    return [(k, *map(int, rng.integers(-20, 21, 2))) for k in range(4) for _ in range(4)]


#: OpenCV's test of a bright rectangle on a dark frame (issue 29 names it
#: test_ipc; it is not among the sources stored here, so the case is re-created
#: from the issue's description).
CV_IPC = "opencv/opencv test_ipc (rectangle, as described in issue 29)"

OPENCV: list[Case] = [
    *[
        Case(
            "opencv",
            f"rectangle_64_{dx:+d}_{dy:+d}",
            CV_IPC,
            f"64² dark frame, one bright 20×14 rectangle moved by ({dx:+d}, {dy:+d}) px: "
            "error < 1 px",
            1.0,
            _cv_rectangle_64(dx, dy),
            note="the frames are exactly equal on the flat background (once taken for "
            "static structure, issue 29); scikit-image finds every shift exactly",
        )
        for dx, dy in ((8, 8), (-8, 8), (8, -8), (-8, -8), (8, 0), (-8, 0), (0, 8), (0, -8))
    ],
    *[
        Case(
            "opencv",
            f"smooth_few_features_212_{i:02d}_{dx:+d}_{dy:+d}",
            CV_PC + " accuracy_real_img",
            f"212² frames of a smooth background with a few sharp strands, integer shift "
            f"({dx:+d}, {dy:+d}), no noise: error ≤ 1 px per axis (Hann window)",
            1.0,
            _cv_smooth(k, dx, dy),
            note="stand-in for TopoStats' file.jpk (212², smooth, issue 29): a smooth "
            "background 10–100 times the height of 2–5 DNA-like strands. A phase "
            "correlation under a Hann window, as OpenCV's phaseCorrelate is tested, finds "
            "every shift; scikit-image's (no window) finds none",
        )
        for i, (k, dx, dy) in enumerate(_smooth_shifts())
    ],
    Case(
        "opencv",
        "rectangle_128x129",
        CV_PC + " CV_PhaseCorrelatorTest::run",
        "129×128 ones with one 11×11 dark square moved by (−10, −20): error < 1 px",
        1.0,
        _cv_rectangles,
        note="OpenCV multiplies a Hann window; afmdrift gets the raw frames",
    ),
    Case(
        "opencv",
        "real_image_129",
        CV_PC + " accuracy_real_img",
        "129×129 crops of a photo 40, 14 px apart (x, y): error ≤ 1 px per axis",
        1.0,
        _cv_real_129,
        note="skimage.data.astronaut (grey) instead of OpenCV's airplane.png; default config",
    ),
    Case(
        "opencv",
        "float32_large_half_overlap",
        CV_PC + " float32_overflow",
        "photo ×5 (bilinear), 16-bit range, float32; left/right ROIs of 2/3 width: "
        "|x| = w/3 ± 1 px, y = 0 ± 1 px",
        1.0,
        _cv_float32_large,
        note="skimage.data.gravel (512²) instead of baboon.png; ROIs 2560×1706",
    ),
]


# --------------------------------------------------------------------------- imreg_dft

IRD = "matejak/imreg_dft tests/regressiontests/Makefile check-translation"


def _ird_translation(reverse: bool) -> Callable[[], Pair]:
    def build() -> Pair:
        img = _skdata("coffee")
        a = img[0:320, 19 : 19 + 560]
        b = img[79 : 79 + 320, 0:560]
        # A scene point at (x, y) is at (x − 19, y) in a and (x, y − 79) in b.
        if reverse:
            return Pair(b.copy(), a.copy(), (-19.0, 79.0))
        return Pair(a.copy(), b.copy(), (19.0, -79.0))

    return build


IMREG_DFT: list[Case] = [
    Case(
        "imreg_dft",
        "translation_forward",
        IRD,
        "photo pair translated by (tx, ty) = (−19, 79) px: integers exactly",
        0.5,
        _ird_translation(False),
        note="skimage.data.coffee (grey) 320×560 crops instead of sample1/sample2.png",
    ),
    Case(
        "imreg_dft",
        "translation_reverse",
        IRD,
        "the same pair swapped: (19, −79) exactly (antisymmetry)",
        0.5,
        _ird_translation(True),
        note="skimage.data.coffee (grey) 320×560 crops instead of sample1/sample2.png",
    ),
]


# --------------------------------------------------------------------------- pystackreg

PSR = "glichtner/pystackreg tests/test_pystackreg.py test_registration_transformation"


def _psr_stack() -> Stack:
    rng = _rng(12)
    shape, n = (256, 256), 10
    # PC12-like: a few large cells on a flat background, 1 nm/px.
    cells = Particles.random((384, 384), pixel_size_nm=1.0, rng=rng, density_per_um2=1.5e5 / 400)
    cells = Particles(cells.x_px, cells.y_px, cells.height_nm, fwhm_px=14.0)
    tex = band_limit(cells.render((384, 384))) + rough_texture(
        (384, 384), pixel_size_nm=1.0, rng=rng, rms_nm=0.3, correlation_length_nm=2.0
    )
    shifter = TextureShifter(tex)
    steps = rng.uniform(-3.0, 3.0, (n - 1, 2))
    pos = np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    frames = [shifter.crop(shape, dx_px=float(x), dy_px=float(y)) for x, y in pos]
    frames = [add_noise(f, snr=20.0, rng=rng) for f in frames]
    return Stack(
        frames,
        [(float(x), float(y)) for x, y in pos],
        config=RegistrationConfig(reference="consecutive"),
    )


PYSTACKREG: list[Case] = [
    Case(
        "pystackreg",
        "pc12_translation_previous",
        PSR,
        "PC12 stack, TRANSLATION, reference 'previous': output equals ImageJ "
        "StackReg's within 1 grey level (we read: positions within 0.2 px)",
        0.2,
        _psr_stack,
        note="10 frames 256² of sparse 14-px cells on a flat background, steps ±3 px, "
        "SNR 20, DriftTracker(reference='consecutive') instead of pc12-unreg.tif",
    ),
]


# --------------------------------------------------------------------------- suite2p

S2P = (
    "MouseLand/suite2p tests/test_modules/test_registration_module.py "
    "test_register_binary_rigid_registration_only"
)


@functools.cache
def _line_grid() -> FloatArray:
    # 256², 16 lines per axis (period 16 px) at 1500 on a zero background.
    x = np.arange(256)
    d = (x % 16).astype(float)
    d = np.minimum(d, 16 - d)
    prof = np.exp(-0.5 * (d / 0.8) ** 2)
    grid = 1500.0 * np.maximum(prof[None, :], prof[:, None])
    grid = band_limit(grid)
    grid.setflags(write=False)
    return grid


def _small_shifts(seed: int, n: int) -> list[tuple[int, int]]:
    """``n`` random non-zero integer shifts with |dx|, |dy| ≤ 7 px (suite2p's rigid range here)."""
    rng = _rng(seed)
    out: list[tuple[int, int]] = []
    while len(out) < n:
        s = (int(rng.integers(-7, 8)), int(rng.integers(-7, 8)))
        if s != (0, 0):
            out.append(s)
    return out


def _grid_shifts() -> list[tuple[int, int]]:
    return _small_shifts(40, 40)


def _wide_grid_shifts() -> list[tuple[int, int]]:
    """40 integer shifts with |dx|, |dy| ≤ 20 px, at least one axis beyond 8
    (more than half the grid's period: not the minimal translation)."""
    rng = _rng(41)
    out: list[tuple[int, int]] = []
    while len(out) < 40:
        s = (int(rng.integers(-20, 21)), int(rng.integers(-20, 21)))
        if max(abs(s[0]), abs(s[1])) > 8:
            out.append(s)
    return out


def _s2p_grid(
    dx: int, dy: int, *, told: bool = False, bound: float | None = None, equivalent: bool = False
) -> Callable[[], Pair]:
    def build() -> Pair:
        g = _line_grid()
        # A tracker's prediction: within a pixel of the truth.
        prior = (dx + 0.8, dy - 0.6) if told else None
        cur = fourier_shift(g, dx_px=dx, dy_px=dy)
        config = RegistrationConfig(
            max_shift_px=bound, lattice="equivalent" if equivalent else "track"
        )
        return Pair(
            g.copy(), cur, (float(dx), float(dy)), prior_px=prior, config=config,
            equivalent_period_px=16.0 if equivalent else None,
        )  # fmt: skip

    return build


@functools.cache
def _neuron_field() -> FloatArray:
    # A two-photon-like field, 1 px ≈ 1 µm: about 90 somata (ellipses of 7–14 px
    # with a dimmer nucleus) on neuropil, 320² for 256² crops.
    rng = _rng(2920)
    rows = cols = 320
    y, x = np.mgrid[:rows, :cols].astype(np.float64)
    field = 0.3 * rough_texture(
        (rows, cols), pixel_size_nm=1.0, rng=rng, rms_nm=1.0, correlation_length_nm=6.0
    )
    for _ in range(90):
        cx, cy = rng.uniform(0, cols), rng.uniform(0, rows)
        a, b, theta = rng.uniform(4, 7), rng.uniform(3.5, 6), rng.uniform(0, math.pi)
        dx = (x - cx + cols / 2) % cols - cols / 2
        dy = (y - cy + rows / 2) % rows - rows / 2
        u = (dx * math.cos(theta) + dy * math.sin(theta)) / a
        v = (-dx * math.sin(theta) + dy * math.cos(theta)) / b
        r2 = u * u + v * v
        field += rng.uniform(1, 3) * np.exp(-(r2**2)) * (1 - 0.6 * np.exp(-4 * r2))
    field = band_limit(field)
    field -= field.min()
    field.setflags(write=False)
    return field


def _s2p_neurons(dx: int, dy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        f = _neuron_field()
        m = 32
        ref = f[m : m + 256, m : m + 256]
        cur = f[m - dy : m - dy + 256, m - dx : m - dx + 256]
        return Pair(ref.copy(), cur.copy(), (float(dx), float(dy)))

    return build


def _neuron_shifts() -> list[tuple[int, int]]:
    return _small_shifts(2921, 20)


SUITE2P: list[Case] = [
    *[
        Case(
            "suite2p",
            f"neurons_{i:02d}_{dx:+d}_{dy:+d}",
            S2P,
            f"two-photon-like field 256², rigid shift ({dx:+d}, {dy:+d}) px: registered "
            "frames identical (the shift exactly)",
            0.5,
            _s2p_neurons(dx, dy),
            note="suite2p's rigid case with small shifts (|d| ≤ 7 px) on a field of "
            "somata over neuropil instead of its line grid (issue 29); integer shifts by "
            "the crop, noise-free",
        )
        for i, (dx, dy) in enumerate(_neuron_shifts())
    ],
    *[
        Case(
            "suite2p",
            f"line_grid_{i:02d}_{dx:+d}_{dy:+d}",
            S2P,
            f"line grid 256², period 16 px, shift ({dx:+d}, {dy:+d}), maximum shift 7 px "
            "(maxregshift): registered frames identical",
            0.5,
            _s2p_grid(dx, dy, bound=7.0),
            note="a perfect lattice that tiles the frame: the data are the same for d and "
            "d + 16 px, so the frames alone cannot identify the shift. suite2p is told its "
            "maximum shift; afmdrift is told the same (max_shift_px = 7, under half the "
            "period), which excludes every other translation (decided_by: bound; issue 38). "
            "Band-limited 1.9-px lines, periodic integer shifts |d| ≤ 7 px",
        )
        for i, (dx, dy) in enumerate(_grid_shifts())
    ],
    *[
        Case(
            "suite2p",
            f"line_grid_wide_{i:02d}_{dx:+d}_{dy:+d}",
            S2P,
            f"line grid 256², period 16 px, shift ({dx:+d}, {dy:+d}), maximum shift 20 px: "
            "registered frames identical (any lattice translation)",
            0.5,
            _s2p_grid(dx, dy, bound=20.0, equivalent=True),
            note="as line_grid_*, shifts up to 20 px: several translations lie within the "
            "bound and register the frames identically, which is all suite2p asserts. "
            "afmdrift is told the bound and asked for the frames registered (lattice = "
            '"equivalent": the translation nearest zero, decided_by: equivalent); a result '
            "a whole number of periods from the shift counts as right (issue 38)",
        )
        for i, (dx, dy) in enumerate(_wide_grid_shifts())
    ],
    *[
        Case(
            "suite2p",
            f"line_grid_prior_{i:02d}_{dx:+d}_{dy:+d}",
            S2P,
            f"line grid 256², period 16 px, shift ({dx:+d}, {dy:+d}), the expected drift "
            "given within a pixel: the minimal translation",
            0.5,
            _s2p_grid(dx, dy, told=True),
            note="as line_grid_*, with the expected drift (a tracker's prediction, "
            "(+0.8, −0.6) px off) given, which decides between the translations",
        )
        for i, (dx, dy) in enumerate(_grid_shifts()[:10])
    ],
]


# --------------------------------------------------------------------------- afspm

AFSPM = "nsulmol/afspm tests/components/drift/test_drift.py test_transform"


def _afspm_facets() -> Pair:
    tex = terrace_texture((320, 320), pixel_size_nm=2.0, rng=_rng(413), terrace_width_nm=60.0)
    s = TextureShifter(tex)
    return Pair(s.crop((256, 256)), s.crop((256, 256), dx_px=4.0, dy_px=13.0), (4.0, 13.0), 2.0)


def _afspm_nanoscope() -> Pair:
    from afmdrift.io import load_image

    img = load_image(str(real_path(NANOSCOPE)))
    h = img.heights_nm
    ref = h[16 : 16 + 224, 16 : 16 + 224]
    cur = h[16 - 13 : 16 - 13 + 224, 16 - 4 : 16 - 4 + 224]
    return Pair(ref.copy(), cur.copy(), (4.0, 13.0), float(img.pixel_size_nm[0]))


AFSPM_CASES: list[Case] = [
    Case(
        "afspm",
        "au_facets_4_13",
        AFSPM,
        "two Au facet contact-mode images, translation (4, 13) px: residual norm < 5 px",
        5.0,
        _afspm_facets,
        tol_norm=True,
        note="terrace (facet-like) texture 256² at 2 nm/px, shifted crops, instead of "
        "Au_facetcontac0000/0003.ibw",
    ),
    Case(
        "afspm",
        "nanoscope_crops_4_13",
        AFSPM,
        "translation (4, 13) px: residual norm < 5 px",
        5.0,
        _afspm_nanoscope,
        tol_norm=True,
        note="real NanoScope frame (../shared/data/real), 224² crops 4, 13 px apart",
        realdata=True,
    ),
]


# --------------------------------------------------------------------------- issue 38

#: Non-rigid frames: whole-image methods agree on one shift (afspm's
#: contact-mode pair asserts a residual norm under 5 px; scikit-image's
#: phase correlation gives the area's mean shift within a pixel or so).
DISTORTED = "issue 38 (afmdrift): whole-image methods on a distorted contact-mode pair"


def _distorted(kind: str, amplitude: float, dx: float, dy: float, real: bool) -> Callable[[], Pair]:
    def build() -> Pair:
        rng = _rng(3810 + int(10 * amplitude) + DISTORTIONS.index(kind))
        if real:
            from afmdrift.io import load_image

            img = load_image(str(real_path(NANOSCOPE)))
            tex = img.heights_nm - float(np.median(img.heights_nm))
            pixel, shape = float(img.pixel_size_nm[0]), (192, 192)
            # a lattice of period about 10 px: the drift stays within the
            # stated bound, which decides the translation
            config = RegistrationConfig(max_shift_px=4.5)
        else:
            tex = terrace_texture((384, 384), pixel_size_nm=2.0, rng=rng, terrace_width_nm=60.0)
            pixel, shape, config = 2.0, (256, 256), None
        ref = add_noise(distorted_crop(tex, shape), snr=10.0, rng=rng)
        cur = distorted_crop(tex, shape, dx_px=dx, dy_px=dy, kind=kind, amplitude_px=amplitude)
        return Pair(ref, add_noise(cur, snr=10.0, rng=rng), (dx, dy), pixel, config=config)

    return build


#: Natural images for large shifts over small overlaps: crops of photographs
#: shipped with scikit-image (read from the installed package).
NATURAL = "scikit-image/scikit-image skimage/registration/tests/test_phase_cross_correlation.py"


@functools.cache
def _natural(name: str) -> FloatArray:
    img = _skdata(name)
    if name == "retina":
        img = img[250:1150, 250:1150]
    out = 100.0 * (img - img.mean()) / img.std()
    out.setflags(write=False)
    return out


def _natural_pair(name: str, n: int, ix: int, iy: int) -> Callable[[], Pair]:
    def build() -> Pair:
        img = _natural(name)
        x0, y0 = max(0, ix), max(0, iy)
        ref = img[y0 : y0 + n, x0 : x0 + n]
        cur = img[y0 - iy : y0 - iy + n, x0 - ix : x0 - ix + n]
        return Pair(ref.copy(), cur.copy(), (float(ix), float(iy)))

    return build


#: (image, frame edge, shift): overlaps of 15–50 % of the frame, each axis at least 64 px.
NATURAL_SHIFTS = [
    ("retina", 450, 100, 350), ("retina", 450, -350, 100), ("retina", 450, -100, -350),
    ("retina", 450, 290, -240), ("retina", 450, -210, 240), ("retina", 450, 180, 200),
    ("hubble_deep_field", 420, 100, 320), ("hubble_deep_field", 420, -330, -90),
    ("hubble_deep_field", 420, 250, -200), ("camera", 256, 120, 150),
    ("camera", 256, -190, 40), ("astronaut", 256, -150, -140), ("astronaut", 256, 60, 185),
    ("coffee", 256, 130, -110), ("gravel", 256, -120, 130), ("brick", 256, 180, 60),
]  # fmt: skip


ISSUE38: list[Case] = [
    *[
        Case(
            "issue38",
            f"distorted_{'nanoscope' if real else 'facets'}_{kind}_{amp:g}px",
            DISTORTED,
            f"a non-rigid frame ({kind}, {amp:g} px across it), moved ({dx:+g}, {dy:+g}) px: "
            "one shift, residual norm < 5 px",
            5.0,
            _distorted(kind, amp, dx, dy, real),
            tol_norm=True,
            note="the current frame distorted by a smooth zero-mean field (afmdrift.testing."
            "distortion_field); the truth is the frame's mean shift. "
            + (
                "Real NanoScope texture (a lattice), the bound stated (max_shift_px = 4.5)"
                if real
                else "Terrace (facet-like) texture 256² at 2 nm/px"
            ),
            realdata=real,
        )
        for real, kind, amp, dx, dy in [
            (False, "bow_x", 2.0, 4.0, 13.0),
            (False, "bow_x", 6.0, -7.3, 5.2),
            (False, "bow_y", 3.0, 4.0, 13.0),
            (False, "bow_y", 8.0, 9.1, -2.4),
            (False, "rotation", 2.0, 4.0, 13.0),
            (False, "bow_x", 10.0, 3.3, 3.3),
            (True, "bow_x", 1.5, 2.2, -1.7),
            (True, "bow_y", 2.0, -1.4, 2.6),
        ]
    ],
    *[
        Case(
            "issue38",
            f"natural_{name}_{ix:+d}_{iy:+d}",
            NATURAL,
            f"{n}² crops of {name} {ix:+d}, {iy:+d} px apart (overlap "
            f"{100 * (n - abs(ix)) * (n - abs(iy)) / n / n:.0f} %): exact (disambiguate=True)",
            0.5,
            _natural_pair(name, n, ix, iy),
            note="large shifts over a small overlap on natural photographs (issue 38), as "
            "scikit-image's disambiguation test does with its eagle",
        )
        for name, n, ix, iy in NATURAL_SHIFTS
    ],
]


# --------------------------------------------------------------------------- issue 13

ISSUE = "issue 13 (afmdrift)"


def _nanoscope_fourier(dx: float, dy: float) -> Callable[[], Pair]:
    def build() -> Pair:
        from afmdrift.io import load_image

        img = load_image(str(real_path(NANOSCOPE)))
        h = img.heights_nm - img.heights_nm.mean()
        cur = fourier_shift(h, dx_px=dx, dy_px=dy)
        m = 16  # cut the wrapped seam away
        return Pair(
            h[m:-m, m:-m].copy(), cur[m:-m, m:-m].copy(), (dx, dy), float(img.pixel_size_nm[0])
        )

    return build


def _nanoscope_crops(dx: float, dy: float) -> Pair:
    from afmdrift.io import load_image

    img = load_image(str(real_path(NANOSCOPE)))
    ix, iy = round(dx), round(dy)
    h = fourier_shift(img.heights_nm - img.heights_nm.mean(), dx_px=dx - ix, dy_px=dy - iy)
    m, n = 16, 224
    ref = img.heights_nm[m : m + n, m : m + n] - img.heights_nm.mean()
    # cur[y, x] = h[y − iy, x − ix]: content moved by the integer part too.
    cur = h[m - iy : m - iy + n, m - ix : m - ix + n]
    return Pair(ref.copy(), cur.copy(), (dx, dy), float(img.pixel_size_nm[0]))


def _gold_quarter() -> Pair:
    rng = _rng(7)
    tex = particle_texture((320, 320), pixel_size_nm=2.0, rng=rng)
    s = TextureShifter(tex)
    ref = s.crop((256, 256))
    cur = s.crop((256, 256), dx_px=5.3, dy_px=-3.7)
    other = particle_texture((128, 128), pixel_size_nm=2.0, rng=rng)
    cur[:128, :128] = other  # a quarter of the frame manipulated
    ref = add_noise(ref, snr=10.0, rng=rng)
    cur = add_noise(cur, snr=10.0, rng=rng)
    return Pair(ref, cur, (5.3, -3.7), 2.0)


def _few_features() -> Pair:
    rng = _rng(5)
    p = Particles(
        x_px=np.array([60.0, 170.0, 95.0, 210.0, 140.0]),
        y_px=np.array([70.0, 50.0, 180.0, 200.0, 120.0]),
        height_nm=np.array([8.0, 10.0, 9.0, 7.0, 11.0]),
        fwhm_px=10.0,
    )
    tex = band_limit(p.render((320, 320)))
    s = TextureShifter(tex)
    ref = add_noise(s.crop((256, 256)), snr=30.0, rng=rng)
    cur = add_noise(s.crop((256, 256), dx_px=6.4, dy_px=-3.2), snr=30.0, rng=rng)
    return Pair(ref, cur, (6.4, -3.2))


def _three_features() -> Pair:
    p = Particles(
        x_px=np.array([100.0, 190.0, 140.0]),
        y_px=np.array([110.0, 150.0, 210.0]),
        height_nm=np.array([5.0, 6.0, 4.0]),
        fwhm_px=6.0,
    )
    s = TextureShifter(band_limit(p.render((320, 320))))
    return Pair(s.crop((256, 256)), s.crop((256, 256), dx_px=4.3, dy_px=-2.6), (4.3, -2.6))


def _hsafm_smooth() -> Pair:
    rng = _rng(200)
    tex = rough_texture((256, 256), pixel_size_nm=0.5, rng=rng, correlation_length_nm=5.0)
    s = TextureShifter(tex)
    ref = add_noise(s.crop((200, 200)), snr=2.0, rng=rng)
    cur = add_noise(s.crop((200, 200), dx_px=1.6, dy_px=-2.3), snr=2.0, rng=rng)
    return Pair(ref, cur, (1.6, -2.3), 0.5)


def _hsafm_streaked() -> Pair:
    from afmdrift.io import load_image

    path = str(real_path(HSAFM))
    a = load_image(f"{path}:18")
    b = load_image(f"{path}:19")
    return Pair(a.heights_nm, b.heights_nm, None, float(a.pixel_size_nm[0]), bound_px=5.0)


def _rough_noise_free(seed: int, dx: float, dy: float) -> Callable[[], Pair]:
    def build() -> Pair:
        tex = rough_texture(
            (280, 280), pixel_size_nm=2.0, rng=_rng(seed), correlation_length_nm=20.0
        )
        cur = fourier_shift(tex, dx_px=dx, dy_px=dy)
        return Pair(tex[12:-12, 12:-12].copy(), cur[12:-12, 12:-12].copy(), (dx, dy), 2.0)

    return build


def _hsafm_movie() -> Stack:
    from afmdrift.io import load_stack

    frames = [f.heights_nm for f in load_stack(str(real_path(HSAFM)))]
    return Stack(frames, None, 0.5, bound_step_px=5.0)


def _hsafm_smooth_snr1(seed: int) -> Callable[[], Pair]:
    def build() -> Pair:
        rng = _rng(1000 + seed)
        tex = rough_texture((256, 256), pixel_size_nm=0.5, rng=rng, correlation_length_nm=5.0)
        d = rng.uniform(-3.0, 3.0, 2)
        s = TextureShifter(tex)
        ref = add_noise(s.crop((200, 200)), snr=1.0, rng=rng)
        cur = add_noise(s.crop((200, 200), dx_px=d[0], dy_px=d[1]), snr=1.0, rng=rng)
        return Pair(ref, cur, (float(d[0]), float(d[1])), 0.5)

    return build


ISSUE13: list[Case] = [
    Case(
        "issue13",
        "nanoscope_fourier_7.6_7.0",
        ISSUE,
        "real NanoScope frame Fourier-shifted by (7.6, 7.0) px: within max(0.5 px, 4σ)",
        0.5,
        _nanoscope_fourier(7.6, 7.0),
        note="periodic sample (lattice ≈ 10 px); the issue saw (0, 0), valid, σ 0.03 px",
        realdata=True,
    ),
    Case(
        "issue13",
        "nanoscope_crops_7.6_7.0",
        ISSUE,
        "real NanoScope frame, 224² crops (7, 7) px apart plus a Fourier shift of "
        "(0.6, 0): within max(0.5 px, 4σ)",
        0.5,
        lambda: _nanoscope_crops(7.6, 7.0),
        note="content enters and leaves at the edges, as in a real scan",
        realdata=True,
    ),
    Case(
        "issue13",
        "gold_quarter_changed",
        ISSUE,
        "gold-like particles 256² (2 nm/px), shift (5.3, −3.7), a quarter replaced, "
        "SNR 10: within 0.5 px",
        0.5,
        _gold_quarter,
    ),
    Case(
        "issue13",
        "few_features_flat",
        ISSUE,
        "five 10-px bumps on a flat background 256², shift (6.4, −3.2), SNR 30: within 0.5 px",
        0.5,
        _few_features,
    ),
    Case(
        "issue13",
        "three_features_noise_free",
        ISSUE,
        "three 6-px bumps on an exactly flat background 256², shift (4.3, −2.6), no "
        "noise: within 0.5 px",
        0.5,
        _three_features,
    ),
    Case(
        "issue13",
        "hsafm_smooth_low_snr",
        ISSUE,
        "smooth rough texture (ℓ = 10 px) 200² at 0.5 nm/px, SNR 2, shift (1.6, −2.3): "
        "within 0.5 px",
        0.5,
        _hsafm_smooth,
    ),
    *[
        Case(
            "issue13",
            f"rough_noise_free_{seed}_{dx:+.2f}_{dy:+.2f}",
            ISSUE,
            f"smooth rough texture (ℓ = 10 px) 256² at 2 nm/px, no noise, shift "
            f"({dx:+.2f}, {dy:+.2f}): within 0.5 px",
            0.5,
            _rough_noise_free(seed, dx, dy),
            note="found by the calibration study (refused by the engine of main c94e9f2); "
            "scikit-image's phase_cross_correlation with normalization=None comes within "
            "0.25 px (with phase normalisation, windowed or not, it does not)",
        )
        for seed, dx, dy in ((0, -3.67, -3.87), (0, 3.9, -3.9), (1, 3.98, 3.85), (1, -3.67, -3.87))
    ],
    *[
        Case(
            "issue13",
            f"hsafm_smooth_snr1_{k:02d}",
            ISSUE,
            "smooth rough texture (ℓ = 10 px) 200² at 0.5 nm/px, SNR 1, random shift "
            "within ±3 px: within 0.5 px, or refused",
            0.5,
            _hsafm_smooth_snr1(k),
            note="no peer meets 0.5 px here (skimage's plain cross-correlation: 0.3–0.9 px)",
            peer_succeeds=False,
        )
        for k in range(12)
    ],
    Case(
        "issue13",
        "hsafm_movie_tracker",
        ISSUE,
        "real HS-AFM movie, 32 frames through DriftTracker (default config; truth "
        "unknown, a few px per frame at most): every accepted increment ≤ 5 px",
        5.0,
        _hsafm_movie,
        note="the issue saw frames 18/19 accepted as a 35 px jump",
        peer_succeeds=False,
        realdata=True,
    ),
    Case(
        "issue13",
        "hsafm_streaked_18_19",
        ISSUE,
        "real HS-AFM frames 18 → 19 (scan-line streaks; truth unknown, drift of a few px "
        "at most): valid only with |d| ≤ 5 px, or refused",
        5.0,
        _hsafm_streaked,
        note="the same pair measured directly; the 35 px jump of the issue came through "
        "DriftTracker (case hsafm_movie_tracker)",
        peer_succeeds=False,
        realdata=True,
    ),
]


#: Peer tests not re-created, and why (printed by benchmarks/peer_battery.py).
NOT_APPLICABLE: dict[str, list[str]] = {
    "skimage": [
        "test_size_one_dimension_input, test_3d_input, test_4d_input_*: afmdrift registers "
        "2-D frames of at least 64×64 px",
        "test_masked_registration_random_masks_non_equal_sizes: afmdrift measures frames "
        "of equal shape",
        "test_correlation with space='fourier' input, invalid-argument and warning tests: "
        "API details, no registration outcome",
    ],
    "opencv": [
        "accuracy_1d_odd_fft: a 129×1 signal (afmdrift needs 64 px on both axes)",
        "Imgproc_DivSpectrums: a spectrum-division unit test",
    ],
    "imreg_dft": [
        "check-similarity, check-similarity2, check-constraints1/2: rotation and scale "
        "(afmdrift measures translation only)",
        "check-tiles: a small image inside a big one (frames of different size)",
    ],
    "pystackreg": [
        "rigid-body, scaled-rotation, affine and bilinear stacks: not translations",
    ],
    "suite2p": [
        "non-rigid and bidirectional-phase regression tests: not a rigid translation",
    ],
    "afspm": [
        "the same test's rotation/scale models and descriptor variants: translation only is "
        "asserted by afspm (Euclidean RANSAC with SIFT or BRIEF)",
    ],
}


ALL_CASES: list[Case] = [
    *SKIMAGE,
    *OPENCV,
    *IMREG_DFT,
    *PYSTACKREG,
    *SUITE2P,
    *AFSPM_CASES,
    *ISSUE13,
    *ISSUE38,
]
CASES_BY_ID: dict[str, Case] = {c.id: c for c in ALL_CASES}
assert len(CASES_BY_ID) == len(ALL_CASES), "case ids must be unique"

PEERS: list[str] = list(dict.fromkeys(c.peer for c in ALL_CASES))


def cases_of(peer: str) -> list[Case]:
    return [c for c in ALL_CASES if c.peer == peer]


#: Cases afmdrift refuses today although the peer meets its own assertion
#: (needless refusals, issue 13). Their peer-tolerance tests are marked
#: xfail(strict=True): once the engine solves a case the test XPASSes, fails,
#: and the entry must be removed. Never list a confident wrong answer here.
_NEEDLESS = "issue 13: needless refusal, the peer solves it: "
KNOWN_REFUSALS: dict[str, str] = {}


# --------------------------------------------------------------------------- test helpers


def params(cases: list[Case], *, peer_test: bool) -> list[object]:
    """pytest parameters of ``cases`` with their marks (realdata, slow, xfail)."""
    import pytest

    out: list[object] = []
    for c in cases:
        if peer_test and not c.peer_succeeds:
            continue
        marks: list[pytest.MarkDecorator] = []
        if c.realdata:
            marks.append(pytest.mark.realdata)
        if c.slow:
            marks.append(pytest.mark.slow)
        if peer_test and c.id in KNOWN_REFUSALS:
            marks.append(pytest.mark.xfail(strict=True, reason=KNOWN_REFUSALS[c.id]))
        out.append(pytest.param(c, id=c.id, marks=marks))
    return out


def describe(o: Outcome) -> str:
    c = o.case
    return (
        f"{c.id} ({c.source}): peer asserts {c.asserts!r}; afmdrift {o.verdict}: "
        f"result {o.result_px} px, error {o.error_px} px, sigma {o.sigma_px} px, "
        f"reason {o.reason!r} {o.detail}"
    )


def assert_no_confident_wrong_answer(case: Case) -> None:
    """(a) No valid result more than max(0.5 px, 4σ) from the truth; refusals name why."""
    import pytest

    o = outcome(case.id)
    if o.verdict == "skipped":
        pytest.skip(o.detail)
    assert o.verdict != "fail", "confident wrong answer: " + describe(o)
    if o.verdict == "refused":
        assert o.reason, "refusal without a reason: " + describe(o)
        assert o.reason.strip(), "refusal without a reason: " + describe(o)


def assert_meets_peer(case: Case) -> None:
    """(b) Where the peer meets its own assertion, afmdrift meets it too."""
    import pytest

    o = outcome(case.id)
    if o.verdict == "skipped":
        pytest.skip(o.detail)
    assert o.verdict == "pass", describe(o)

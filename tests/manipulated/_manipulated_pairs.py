"""Manipulated frames (issue 29): the paper's own case, nanomanipulation.

Yang et al. (2008) measure drift between frames taken before and after a
tip moved particles around. Each pair here is a reference and a current
frame of one texture, the current one shifted by a known drift and then
changed in one of :data:`KINDS` of ways; both frames get white noise (SNR
10), and the current one a z offset and a tilt. The untouched part of the
frame moved by exactly the drift, so a valid result must give it.

Textures (:data:`TEXTURES`): synthetic ones of ``afmdrift.testing`` (gold
particles on a flat substrate, graphite-like terraces) and the real files of
``../shared/data/real`` (the NanoScope frame, mirror-tiled into a periodic
512² texture as the issue's tester did, and cut natively into 192² frames;
HS-AFM frame 0 cut into 168² frames). Frames are cut out of a periodic
texture shifted in Fourier space (exact sub-pixel shifts); the ``tester``
arrangement instead shifts the whole frame circularly, so content wraps
around, as in the issue's report.

``tests/manipulated/test_manipulated.py`` and
``benchmarks/manipulated_manipulated_pairs.py`` both build their pairs here.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.testing import (
    TextureShifter,
    add_noise,
    add_plane,
    fourier_shift,
    particle_texture,
    terrace_texture,
)

FloatArray = npt.NDArray[np.float64]

#: ``../shared/data/real`` next to the repository (read in place, never copied).
REAL_DATA_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"
NANOSCOPE = "nanoscope3a_15um.002"
HSAFM = "hsafm_sample_0.asd"

#: Height SNR of both frames (std of heights / std of noise).
SNR = 10.0


class MissingDataError(Exception):
    """A real-data file is absent (tests skip, the benchmark says so)."""


@dataclass(frozen=True)
class Texture:
    """A periodic texture and how frames are cut from it."""

    name: str
    heights: FloatArray  # periodic, heights in nm
    frame: int  # frame edge, px
    max_shift_px: float  # largest drift per axis
    pixel_size_nm: float
    realdata: bool = False
    #: Shift the whole frame circularly (content wraps around) instead of
    #: cutting it out of a larger texture.
    wrap: bool = False


@dataclass(frozen=True)
class Pair:
    """Reference, manipulated current frame and the true drift (px)."""

    texture: str
    kind: str
    seed: int
    reference: FloatArray
    current: FloatArray
    truth: tuple[float, float]
    pixel_size_nm: float
    #: Share of the current frame the manipulation changed.
    changed: float


# --------------------------------------------------------------------------- textures


def _real(name: str) -> Path:
    p = REAL_DATA_DIR / name
    if not p.is_file():
        raise MissingDataError(f"real AFM file {name} not found in {REAL_DATA_DIR.resolve()}")
    return p


def _mirror_tiled(h: FloatArray) -> FloatArray:
    """A periodic texture twice the size of ``h``: ``h`` and its mirror images
    (continuous at every seam)."""
    top = np.hstack([h, h[:, ::-1]])
    return np.vstack([top, top[::-1, :]])


def _levelled(h: FloatArray) -> FloatArray:
    out: FloatArray = h - np.median(h, axis=1, keepdims=True)
    return out - out.mean()


@functools.cache
def texture(name: str) -> Texture:
    """The texture ``name`` of :data:`TEXTURES` (built once per process)."""
    rng = np.random.default_rng(2900 + TEXTURES.index(name))
    if name == "gold":
        tex = particle_texture((600, 600), pixel_size_nm=4.0, rng=rng, density_per_um2=80.0)
        return Texture(name, tex, 512, 30.0, 4.0)
    if name == "terraces":
        tex = terrace_texture((600, 600), pixel_size_nm=4.0, rng=rng, terrace_width_nm=120.0)
        return Texture(name, tex, 512, 30.0, 4.0)
    if name == "gold_tester":
        tex = particle_texture((512, 512), pixel_size_nm=5.0, rng=rng, density_per_um2=80.0)
        return Texture(name, tex, 512, 30.0, 5.0, wrap=True)
    from afmdrift.io import load_image

    if name in ("nanoscope_tiled", "nanoscope"):
        img = load_image(str(_real(NANOSCOPE)))
        h = _levelled(img.heights_nm)
        px = float(img.pixel_size_nm[0])
        if name == "nanoscope_tiled":
            return Texture(name, _mirror_tiled(h), 512, 30.0, px, realdata=True, wrap=True)
        return Texture(name, h, 192, 30.0, px, realdata=True)
    if name == "hsafm":
        img = load_image(f"{_real(HSAFM)}:0")
        h = _levelled(img.heights_nm)
        return Texture(name, h, 168, 15.0, float(img.pixel_size_nm[0]), realdata=True)
    raise ValueError(f"unknown texture {name!r}; known: {', '.join(TEXTURES)}")


#: Generated textures first, then the real ones.
TEXTURES: tuple[str, ...] = (
    "gold",
    "terraces",
    "gold_tester",
    "nanoscope_tiled",
    "nanoscope",
    "hsafm",
)
REAL_TEXTURES = frozenset({"nanoscope_tiled", "nanoscope", "hsafm"})


# --------------------------------------------------------------------------- manipulations


def _soft_disc(shape: tuple[int, int], x: float, y: float, radius: float) -> FloatArray:
    """1 inside a disc, 0 outside, with a 2-px ramp at its edge."""
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    r = np.hypot(xx - x, yy - y)
    out: FloatArray = np.clip((radius - r) / 2.0 + 0.5, 0.0, 1.0)
    return out


def _smooth(img: FloatArray, sigma: float) -> FloatArray:
    from scipy.ndimage import gaussian_filter

    out: FloatArray = gaussian_filter(img, sigma, mode="reflect")
    return out


def quadrant(cur: FloatArray, rng: np.random.Generator) -> float:
    """The issue's case: the top-left quadrant replaced by a mirrored,
    circularly shifted copy of itself (a quarter of the frame)."""
    n = cur.shape[0] // 2
    q = cur[:n, :n][:, ::-1]
    shift = (int(rng.integers(n // 6, n - n // 6)), int(rng.integers(n // 6, n - n // 6)))
    cur[:n, :n] = np.roll(q, shift, axis=(0, 1))
    return 0.25


def patches(cur: FloatArray, rng: np.random.Generator) -> float:
    """Six square patches (an eighth to a fifth of the frame edge) replaced by
    content copied from elsewhere in the frame."""
    rows, cols = cur.shape
    src = cur.copy()
    changed = np.zeros(cur.shape, dtype=bool)
    for _ in range(6):
        s = int(rng.integers(rows // 8, rows // 5))
        t, left = int(rng.integers(0, rows - s)), int(rng.integers(0, cols - s))
        st, sl = int(rng.integers(0, rows - s)), int(rng.integers(0, cols - s))
        cur[t : t + s, left : left + s] = src[st : st + s, sl : sl + s]
        changed[t : t + s, left : left + s] = True
    return float(changed.mean())


def moved(cur: FloatArray, rng: np.random.Generator) -> float:
    """Eight discs (particles, or whatever lies there) pushed by the tip:
    each cut out, its place filled with the local background, and set down
    10–40 px away."""
    rows, cols = cur.shape
    changed = np.zeros(cur.shape)
    background = _smooth(cur, rows / 16)
    for _ in range(8):
        radius = rows / float(rng.uniform(16, 24))
        x, y = rng.uniform(radius, cols - radius), rng.uniform(radius, rows - radius)
        step, angle = rng.uniform(10, 40), rng.uniform(0, 2 * math.pi)
        nx = float(np.clip(x + step * math.cos(angle), radius, cols - radius))
        ny = float(np.clip(y + step * math.sin(angle), radius, rows - radius))
        piece = np.roll(cur, (round(ny - y), round(nx - x)), axis=(0, 1))
        hole = _soft_disc(cur.shape, x, y, radius)
        cur[:] = hole * background + (1 - hole) * cur
        dest = _soft_disc(cur.shape, nx, ny, radius)
        cur[:] = dest * piece + (1 - dest) * cur
        changed = np.maximum(changed, np.maximum(hole, dest))
    return float(changed.mean())


def new_particle(cur: FloatArray, rng: np.random.Generator) -> float:
    """One large new particle deposited (a twelfth of the frame edge wide, five
    times the texture's height spread)."""
    rows, cols = cur.shape
    fwhm = rows / 12
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    x, y = rng.uniform(fwhm, cols - fwhm), rng.uniform(fwhm, rows - fwhm)
    yy, xx = np.mgrid[0:rows, 0:cols]
    bump = np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / sigma**2)
    cur += 5.0 * float(cur.std()) * bump
    return float(np.mean(bump > 0.05))


def scratch(cur: FloatArray, rng: np.random.Generator) -> float:
    """A scratch across the frame: a groove 4 px wide (FWHM), three times the
    texture's height spread deep, along a random direction."""
    rows, cols = cur.shape
    angle = rng.uniform(0, math.pi)
    x0, y0 = rng.uniform(cols / 4, 3 * cols / 4), rng.uniform(rows / 4, 3 * rows / 4)
    yy, xx = np.mgrid[0:rows, 0:cols]
    dist = (xx - x0) * math.sin(angle) - (yy - y0) * math.cos(angle)
    groove = np.exp(-0.5 * (dist / (4.0 / 2.355)) ** 2)
    cur -= 3.0 * float(cur.std()) * groove
    return float(np.mean(groove > 0.05))


KINDS: dict[str, Callable[[FloatArray, np.random.Generator], float]] = {
    "quadrant": quadrant,
    "patches": patches,
    "moved": moved,
    "new_particle": new_particle,
    "scratch": scratch,
}


# --------------------------------------------------------------------------- pairs


def make_pair(texture_name: str, kind: str, seed: int) -> Pair:
    """Pair number ``seed`` of one texture and manipulation (deterministic)."""
    tex = texture(texture_name)
    rng = np.random.default_rng([29, TEXTURES.index(texture_name), list(KINDS).index(kind), seed])
    d = rng.uniform(-tex.max_shift_px, tex.max_shift_px, 2)
    n = tex.frame
    if tex.wrap:
        rows, cols = tex.heights.shape
        y0, x0 = int(rng.integers(0, rows - n + 1)), int(rng.integers(0, cols - n + 1))
        base = np.roll(tex.heights, (-y0, -x0), axis=(0, 1))[:n, :n]
        ref = base.copy()
        cur = fourier_shift(base, dx_px=float(d[0]), dy_px=float(d[1]))
    else:
        shifter = _shifter(texture_name)
        ref = shifter.crop((n, n))
        cur = shifter.crop((n, n), dx_px=float(d[0]), dy_px=float(d[1]))
    changed = KINDS[kind](cur, rng)
    ref = add_noise(ref, snr=SNR, rng=rng)
    cur = add_noise(cur, snr=SNR, rng=rng)
    spread = float(ref.std())
    cur = add_plane(
        cur,
        offset_nm=float(rng.uniform(-20, 20)) * spread,
        slope_x=float(rng.uniform(-0.01, 0.01)) * spread,
        slope_y=float(rng.uniform(-0.01, 0.01)) * spread,
    )
    return Pair(
        texture_name, kind, seed, ref, cur, (float(d[0]), float(d[1])), tex.pixel_size_nm, changed
    )


@functools.cache
def _shifter(texture_name: str) -> TextureShifter:
    return TextureShifter(texture(texture_name).heights)


# --------------------------------------------------------------------------- outcomes


@dataclass(frozen=True)
class Outcome:
    """afmdrift's answer on one pair."""

    pair: Pair
    valid: bool
    result_px: tuple[float, float]
    sigma_px: tuple[float, float]
    reason: str | None

    @property
    def error_px(self) -> tuple[float, float]:
        return (
            self.result_px[0] - self.pair.truth[0],
            self.result_px[1] - self.pair.truth[1],
        )

    @property
    def wrong(self) -> bool:
        """Valid, and more than max(0.5 px, 4σ) from the truth on an axis."""
        return self.valid and any(
            abs(e) > max(0.5, 4.0 * s) for e, s in zip(self.error_px, self.sigma_px, strict=True)
        )

    def describe(self) -> str:
        p = self.pair
        return (
            f"{p.texture}/{p.kind}/seed {p.seed}: truth ({p.truth[0]:.2f}, {p.truth[1]:.2f}) "
            f"px, {100 * p.changed:.0f} % changed; "
            + (
                f"valid ({self.result_px[0]:.3f}, {self.result_px[1]:.3f}) px, error "
                f"({self.error_px[0]:+.3f}, {self.error_px[1]:+.3f}) px, sigma "
                f"({self.sigma_px[0]:.3f}, {self.sigma_px[1]:.3f}) px"
                if self.valid
                else f"refused: {self.reason}"
            )
        )


def measure(pair: Pair) -> Outcome:
    """``measure_drift`` on the pair, default configuration, no prior (the
    coarse alignment finds it, as ``afmdrift measure`` does)."""
    from afmdrift.registration import measure_drift

    r = measure_drift(pair.reference, pair.current, pixel_size_nm=pair.pixel_size_nm)
    px = pair.pixel_size_nm
    return Outcome(
        pair,
        bool(r.valid),
        (float(r.dx_px), float(r.dy_px)),
        (r.sigma_x_nm / px, r.sigma_y_nm / px),
        r.reason,
    )


@dataclass(frozen=True)
class Cell:
    """The summary of one texture and manipulation."""

    texture: str
    kind: str
    pairs: int
    refused: int
    wrong: int
    rms_px: float  # RMS error of the valid results, both axes pooled
    max_px: float
    changed: float  # mean share of the frame changed

    @classmethod
    def of(cls, outcomes: list[Outcome]) -> Cell:
        p = outcomes[0].pair
        errs = np.array([o.error_px for o in outcomes if o.valid]).reshape(-1)
        return cls(
            p.texture,
            p.kind,
            len(outcomes),
            sum(not o.valid for o in outcomes),
            sum(o.wrong for o in outcomes),
            float(np.sqrt(np.mean(errs**2))) if errs.size else math.nan,
            float(np.max(np.abs(errs))) if errs.size else math.nan,
            float(np.mean([o.pair.changed for o in outcomes])),
        )

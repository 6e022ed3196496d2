"""Uncertainty calibration of issue 13: known sub-pixel shifts of real and synthetic textures.

A texture is shifted by a known sub-pixel amount, both frames get independent
white noise at a given SNR (``afmdrift.testing.add_noise``: std of heights
over std of noise), and :func:`afmdrift.registration.measure_drift` measures
the pair. Over many shifts this gives the RMS error per texture and SNR and
the σ calibration: the fraction of per-axis errors within 1σ, 2σ and 3σ of
the stated uncertainty (σ in px per axis is ``sigma_x_nm / pixel_size_x_nm``).
Issue 13 wants 90–98 % within 2σ (a Gaussian gives 68 / 95 / 99.7 %).

Shifting a real (non-periodic) frame: the frame is mirrored to a 2N × 2N
periodic image without jumps at its edges, Fourier-shifted
(``afmdrift.testing.fourier_shift``), cut back to N × N and then both frames
lose a margin of ``MARGIN`` px, so neither the wrapped content nor the
ringing of the mirror seams enters (content enters and leaves at the edges
as in a real scan). Synthetic textures are periodic and band-limited: their
Fourier shift is exact.

``benchmarks/calibration.py`` prints the tables; ``test_calibration_realdata.py``
runs a small version on the real files.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from _battery import HSAFM, NANOSCOPE, MissingDataError, real_path

from afmdrift.errors import InputError
from afmdrift.registration import RegistrationConfig, measure_drift
from afmdrift.testing import (
    add_noise,
    fourier_shift,
    particle_texture,
    rough_texture,
    terrace_texture,
)

FloatArray = npt.NDArray[np.float64]

#: Px cut from every edge after the shift (the largest shift is MAX_SHIFT_PX).
MARGIN = 12
MAX_SHIFT_PX = 4.0
SNRS: tuple[float, ...] = (math.inf, 10.0, 5.0)


@dataclass(frozen=True)
class Texture:
    name: str
    heights: FloatArray
    pixel_size_nm: float
    periodic: bool
    config: RegistrationConfig | None = None


@dataclass(frozen=True)
class Trial:
    truth: tuple[float, float]
    valid: bool
    result: tuple[float, float] | None
    sigma: tuple[float, float] | None
    reason: str | None


@dataclass(frozen=True)
class Summary:
    texture: str
    snr: float
    trials: int
    valid: int
    rms_px: float  # RMS of the per-axis errors of valid results (both axes pooled)
    max_px: float
    within: tuple[float, float, float]  # fraction of axis errors within 1, 2, 3 σ
    median_sigma_px: float
    confident_wrong: int  # valid with an axis error > max(0.5 px, 4σ)
    reasons: tuple[str, ...]


def shift_frame(h: FloatArray, dx: float, dy: float, *, periodic: bool) -> FloatArray:
    """``h`` with its content moved by ``(dx, dy)`` px (before the margin is cut)."""
    if periodic:
        return fourier_shift(h, dx_px=dx, dy_px=dy)
    rows, cols = h.shape
    m = np.block([[h, h[:, ::-1]], [h[::-1, :], h[::-1, ::-1]]])
    return fourier_shift(m, dx_px=dx, dy_px=dy)[:rows, :cols]


def trial(tex: Texture, dx: float, dy: float, snr: float, rng: np.random.Generator) -> Trial:
    h = tex.heights - tex.heights.mean()
    cur = shift_frame(h, dx, dy, periodic=tex.periodic)
    ref = h
    if math.isfinite(snr):
        ref = add_noise(ref, snr=snr, rng=rng)
        cur = add_noise(cur, snr=snr, rng=rng)
    m = MARGIN
    ref, cur = ref[m:-m, m:-m], cur[m:-m, m:-m]
    try:
        r = measure_drift(ref, cur, pixel_size_nm=tex.pixel_size_nm, config=tex.config)
    except InputError as err:
        return Trial((dx, dy), False, None, None, f"{type(err).__name__}: {err}")
    if not r.valid:
        return Trial((dx, dy), False, None, None, r.reason)
    return Trial(
        (dx, dy),
        True,
        (float(r.dx_px), float(r.dy_px)),
        (r.sigma_x_nm / tex.pixel_size_nm, r.sigma_y_nm / tex.pixel_size_nm),
        None,
    )


def summarise(tex: str, snr: float, trials: Sequence[Trial]) -> Summary:
    errs: list[float] = []
    sig: list[float] = []
    wrong = 0
    for t in trials:
        if not t.valid or t.result is None or t.sigma is None:
            continue
        e = [abs(t.result[i] - t.truth[i]) for i in (0, 1)]
        errs += e
        sig += list(t.sigma)
        if any(e[i] > max(0.5, 4.0 * t.sigma[i]) for i in (0, 1)):
            wrong += 1
    e_arr, s_arr = np.array(errs), np.array(sig)
    n_valid = sum(t.valid for t in trials)
    if e_arr.size:
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(s_arr > 0, e_arr / s_arr, np.where(e_arr > 0, np.inf, 0.0))
        within = tuple(float(np.mean(z <= k)) for k in (1.0, 2.0, 3.0))
        rms, mx, med = (
            float(np.sqrt(np.mean(e_arr**2))),
            float(e_arr.max()),
            float(np.median(s_arr)),
        )
    else:
        within, rms, mx, med = (math.nan,) * 3, math.nan, math.nan, math.nan
    reasons = tuple(sorted({(t.reason or "")[:90] for t in trials if not t.valid}))
    return Summary(tex, snr, len(trials), n_valid, rms, mx, within, med, wrong, reasons)  # type: ignore[arg-type]


def run(tex: Texture, snr: float, n: int, seed: int = 0) -> tuple[Summary, list[Trial]]:
    """``n`` random shifts within ±MAX_SHIFT_PX per axis at one SNR."""
    rng = np.random.default_rng([seed, int(1000 * snr) if math.isfinite(snr) else 0])
    shifts = rng.uniform(-MAX_SHIFT_PX, MAX_SHIFT_PX, (n, 2))
    trials = [trial(tex, float(dx), float(dy), snr, rng) for dx, dy in shifts]
    return summarise(tex.name, snr, trials), trials


# --------------------------------------------------------------------------- textures


@functools.cache
def nanoscope() -> Texture:
    from afmdrift.io import load_image

    img = load_image(str(real_path(NANOSCOPE)))
    return Texture("NanoScope .002 (256², 58.6 nm/px)", img.heights_nm, img.pixel_size_nm[0], False)


@functools.cache
def hsafm(frame: int) -> Texture:
    from afmdrift.io import load_image

    img = load_image(f"{real_path(HSAFM)}:{frame}")
    return Texture(
        f"HS-AFM .asd frame {frame} (200², 0.5 nm/px)", img.heights_nm, img.pixel_size_nm[0], False
    )


def real_textures(hsafm_frames: Sequence[int] = (3, 8, 12)) -> list[Texture]:
    """The real textures; raises :class:`MissingDataError` when a file is absent."""
    return [nanoscope(), *(hsafm(f) for f in hsafm_frames)]


def synthetic_textures() -> list[Texture]:
    rng = np.random.default_rng(2026)
    shape = (280, 280)
    return [
        Texture(
            "particles 280² (2 nm/px)",
            particle_texture(shape, pixel_size_nm=2.0, rng=rng),
            2.0,
            True,
        ),
        Texture(
            "rough ℓ = 10 px 280² (2 nm/px)",
            rough_texture(shape, pixel_size_nm=2.0, rng=rng, correlation_length_nm=20.0),
            2.0,
            True,
        ),
        Texture(
            "terraces 280² (2 nm/px)",
            terrace_texture(shape, pixel_size_nm=2.0, rng=rng),
            2.0,
            True,
        ),
    ]


def all_textures(*, real: bool = True) -> list[Texture]:
    out: list[Texture] = []
    if real:
        with contextlib.suppress(MissingDataError):
            out += real_textures()
    return out + synthetic_textures()


Runner = Callable[[Texture, float, int], tuple[Summary, list[Trial]]]

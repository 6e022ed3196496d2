"""A stated bound on the drift, and registration of a periodic sample (issue 38).

``max_shift_px`` is information the user has (suite2p's ``maxregshift``):
lattice translations beyond it are excluded, so a bound under half a period
decides (``decided_by: "bound"``), none within it refuses, and a result
beyond it is refused. ``lattice = "equivalent"`` asks for the frames
registered, not the drift tracked: the tied translation nearest zero (or the
prior) is taken (``decided_by: "equivalent"``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from afmdrift.config import RegistrationConfig
from afmdrift.registration import measure_drift
from afmdrift.registration._lattice import repeat_vectors
from afmdrift.testing import TextureShifter, add_noise, lattice_texture, rough_texture

FRAME = (224, 224)


def _texture(seed: int = 5) -> np.ndarray:
    return lattice_texture((320, 320), rng=np.random.default_rng(seed), vacancy_fraction=0.0)


def _pair(texture: np.ndarray, d: tuple[float, float], seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    shifter = TextureShifter(texture)
    ref = add_noise(shifter.crop(FRAME), snr=8.0, rng=rng)
    cur = add_noise(shifter.crop(FRAME, dx_px=d[0], dy_px=d[1]), snr=8.0, rng=rng)
    return ref, cur


def _lattice_off(
    got: tuple[float, float], truth: tuple[float, float], vectors: np.ndarray
) -> float:
    """Distance from ``got`` to the nearest lattice translation of ``truth``."""
    v1 = vectors[0]
    v2 = next(v for v in vectors[1:] if abs(v1[0] * v[1] - v1[1] * v[0]) > 1.0)
    best = math.inf
    for i in range(-4, 5):
        for j in range(-4, 5):
            p = np.asarray(truth) + i * v1 + j * v2
            best = min(best, math.hypot(got[0] - p[0], got[1] - p[1]))
    return best


SMALL = [(3.4, -1.2), (-2.6, 2.1), (1.3, 3.7), (-3.9, -0.4)]


@pytest.mark.parametrize("d", SMALL)
def test_a_bound_under_half_a_period_decides(d: tuple[float, float]) -> None:
    """A perfect lattice (shortest period 11.5 px): alone, the pair is
    refused as ambiguous; told that the drift is at most 4.5 px per axis,
    the one translation within it is measured, right to 0.1 px."""
    ref, cur = _pair(_texture(), d, seed=int(10 * d[0]) % 97)
    alone = measure_drift(ref, cur, pixel_size_nm=1.0)
    assert not alone.valid
    assert alone.reason is not None
    assert alone.reason.startswith("ambiguous")
    assert "--max-shift-px" in alone.reason  # the refusal says what would decide
    r = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(max_shift_px=4.5))
    assert r.valid, r.reason
    assert r.decided_by == "bound"
    assert math.hypot(r.dx_px - d[0], r.dy_px - d[1]) < 0.1, (r.dx_px, r.dy_px, d)
    assert r.alternatives_px  # the translations the bound excluded
    assert all(max(abs(a), abs(b)) > 4.5 for a, b in r.alternatives_px)


def test_no_translation_within_the_bound_is_refused_saying_so() -> None:
    """Half a period off (5.7 px): every translation lies beyond a 2 px bound."""
    tex = _texture()
    v = repeat_vectors(tex)[0]
    d = (float(v[0]) / 2, float(v[1]) / 2)
    ref, cur = _pair(tex, d, seed=4)
    r = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(max_shift_px=2.0))
    assert not r.valid
    assert r.reason is not None
    assert r.reason.startswith("beyond the bound"), r.reason


@pytest.mark.parametrize("d", [(9.3, -14.2), (-16.4, 3.1), (12.2, 12.8)])
def test_equivalent_registers_the_frames_and_says_so(d: tuple[float, float]) -> None:
    """Shifts of more than half a period with a bound of 20 px: several
    translations lie within it. Tracking refuses (the drift is not known);
    ``lattice = "equivalent"`` takes the one nearest zero, a whole lattice
    translation from the shift, and says decided_by: equivalent."""
    tex = _texture()
    ref, cur = _pair(tex, d, seed=7)
    track = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(max_shift_px=20))
    assert not track.valid
    assert track.reason is not None
    assert track.reason.startswith("ambiguous"), track.reason
    assert all(max(abs(a), abs(b)) <= 20.5 for a, b in track.lattice_px)
    cfg = RegistrationConfig(max_shift_px=20, lattice="equivalent")
    r = measure_drift(ref, cur, pixel_size_nm=1.0, config=cfg)
    assert r.valid, r.reason
    assert r.decided_by == "equivalent"
    assert _lattice_off((r.dx_px, r.dy_px), d, repeat_vectors(tex)) < 0.15
    assert r.alternatives_px
    assert r.ambiguity_px > 5
    # nearest zero among the tied translations
    assert all(math.hypot(r.dx_px, r.dy_px) <= math.hypot(a, b) + 0.5 for a, b in r.alternatives_px)


def test_equivalent_without_a_bound_takes_the_translation_nearest_zero() -> None:
    tex = _texture()
    d = (21.7, -8.2)
    ref, cur = _pair(tex, d, seed=9)
    r = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(lattice="equivalent"))
    assert r.valid, r.reason
    assert r.decided_by == "equivalent"
    assert _lattice_off((r.dx_px, r.dy_px), d, repeat_vectors(tex)) < 0.15
    assert math.hypot(r.dx_px, r.dy_px) < 8.0


def test_a_bound_changes_nothing_where_the_content_decides_and_refuses_beyond_it() -> None:
    """A rough texture (no lattice) shifted (9.3, −6.4) px: a bound of 12 px
    gives the same numbers as none; a bound of 5 px is contradicted by the
    frames and the pair is refused, naming the bound."""
    rng = np.random.default_rng(11)
    tex = rough_texture((320, 320), pixel_size_nm=1.0, rng=rng, correlation_length_nm=4.0)
    shifter = TextureShifter(tex)
    ref = add_noise(shifter.crop(FRAME), snr=8.0, rng=rng)
    cur = add_noise(shifter.crop(FRAME, dx_px=9.3, dy_px=-6.4), snr=8.0, rng=rng)
    free = measure_drift(ref, cur, pixel_size_nm=1.0)
    wide = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(max_shift_px=12))
    assert free.valid
    assert wide.valid
    assert (wide.dx_px, wide.dy_px, wide.decided_by) == (free.dx_px, free.dy_px, "content")
    tight = measure_drift(ref, cur, pixel_size_nm=1.0, config=RegistrationConfig(max_shift_px=5))
    assert not tight.valid
    assert tight.reason is not None
    assert tight.reason.startswith("beyond the bound")
    assert "max_shift_px = 5" in tight.reason


def test_configuration_separates_the_bound_from_the_block_search() -> None:
    """``max_shift_px`` is a bound on the drift (any size); the block
    search half-width is ``block_search_px`` and keeps its limit."""
    assert RegistrationConfig(max_shift_px=350).max_shift_px == 350
    with pytest.raises(ValidationError, match="block_search_px"):
        RegistrationConfig(block_search_px=63)
    with pytest.raises(ValidationError, match="lattice"):
        RegistrationConfig(lattice="any")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="max_shift_px"):
        RegistrationConfig(max_shift_px=0)

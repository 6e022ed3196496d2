"""Manipulated frames (issue 29): a part of the current frame changed (a
replaced quadrant, scattered patches, moved particles, a new particle, a
scratch), the rest shifted by a known drift, SNR 10, a z offset and a tilt.
The untouched part must be measured: valid, and within 0.1 px of the drift.

The pairs are built in ``_manipulated_pairs.py``, which ``benchmarks/manipulated_battery.py``
runs at full size (the table per texture and manipulation). The default run
measures two pairs per generated texture and manipulation and one per real
texture; ``slow`` adds more seeds.
"""

from __future__ import annotations

import pytest
from _manipulated_pairs import KINDS, REAL_TEXTURES, MissingDataError, make_pair, measure

#: Largest error of a valid result on the untouched part (px).
TOLERANCE_PX = 0.1

#: Textures whose every pair must be measured. The NanoScope lattice (period
#: about 10 px) cut natively into 192² frames has its own test below: with
#: shifts up to 30 px and a changed area, its content does not always decide
#: the lattice translation (6 of 100 pairs refused as ambiguous in the
#: benchmark; 11 of 100 were valid and one or more periods off before).
TEXTURES = ("gold", "terraces", "gold_tester", "nanoscope_tiled", "hsafm")


def _params(seeds: range, *, slow: bool) -> list[object]:
    out: list[object] = []
    for texture in TEXTURES:
        for kind in KINDS:
            for seed in seeds if texture not in REAL_TEXTURES else seeds[:1]:
                marks = [pytest.mark.realdata] if texture in REAL_TEXTURES else []
                if slow:
                    marks.append(pytest.mark.slow)
                out.append(
                    pytest.param(texture, kind, seed, id=f"{texture}-{kind}-{seed}", marks=marks)
                )
    return out


def _check(texture: str, kind: str, seed: int) -> None:
    try:
        pair = make_pair(texture, kind, seed)
    except MissingDataError as err:
        pytest.skip(str(err))
    o = measure(pair)
    assert o.valid, o.describe()
    assert max(abs(e) for e in o.error_px) <= TOLERANCE_PX, o.describe()


@pytest.mark.parametrize(("texture", "kind", "seed"), _params(range(2), slow=False))
def test_untouched_part_is_measured(texture: str, kind: str, seed: int) -> None:
    _check(texture, kind, seed)


@pytest.mark.parametrize(("texture", "kind", "seed"), _params(range(2, 12), slow=True))
def test_untouched_part_is_measured_more_seeds(texture: str, kind: str, seed: int) -> None:
    _check(texture, kind, seed)


@pytest.mark.realdata
@pytest.mark.parametrize("kind", list(KINDS))
def test_manipulated_lattice_is_never_a_period_off(kind: str) -> None:
    """Regression (issue 29): the native NanoScope frames (a lattice) with a
    changed area gave 27 of 200 valid results one or more periods off (up to
    44 px). A result is now right, or refused as ambiguous between lattice
    translations; three seeds per manipulation, two of them measured."""
    measured = 0
    for seed in range(3):
        try:
            pair = make_pair("nanoscope", kind, seed)
        except MissingDataError as err:
            pytest.skip(str(err))
        o = measure(pair)
        if o.valid:
            measured += 1
            assert max(abs(e) for e in o.error_px) <= TOLERANCE_PX, o.describe()
        else:
            assert o.reason is not None
            assert o.reason.startswith("ambiguous"), o.describe()
    assert measured >= 2

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

#: The NanoScope lattice (period about 10 px) cut natively into 192² frames
#: with shifts up to 30 px is left to the lattice work of issue 29 (a valid
#: result a lattice translation off); the benchmark reports it.
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

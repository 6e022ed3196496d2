"""Known shifts of a lattice texture near half and a whole period (issue 29).

``benchmarks/lattice_shifts.py`` measures every pair; the tests in
``test_registration_lattice.py`` measure the ones that were a period off
before the lattice decision and a spread of others. Both build them here.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

from afmdrift.testing import add_noise, fourier_shift

FloatArray = npt.NDArray[np.float64]

#: Period of the real NanoScope frame's lattice along its shortest vector (px).
NANOSCOPE_PERIOD_PX = 10.3
#: The groups: label and the shift in periods.
GROUPS = (("half a period", 0.5), ("a whole period", 1.0))


def shifted_pairs(
    heights: FloatArray, *, period_px: float, pairs: int = 30, seed: int = 2, size: int = 224
) -> Iterator[tuple[str, int, tuple[float, float], FloatArray, FloatArray]]:
    """``(group, index, truth, reference, current)`` for ``pairs`` shifts per
    group of :data:`GROUPS`, in random directions, ±0.5 px per axis: ``size``²
    crops of ``heights`` (16 px in from its corner), the integer part of the
    shift by the crop, the fraction by a Fourier shift, white noise at SNR
    5–10 on both frames."""
    h0 = heights - heights.mean()
    rng = np.random.default_rng(seed)
    m = 16
    for label, scale in GROUPS:
        for k in range(pairs):
            angle = rng.uniform(0, 2 * math.pi)
            d = scale * period_px * np.array([math.cos(angle), math.sin(angle)])
            d += rng.uniform(-0.5, 0.5, 2)
            ix, iy = round(d[0]), round(d[1])
            h = fourier_shift(h0, dx_px=d[0] - ix, dy_px=d[1] - iy)
            ref = h0[m : m + size, m : m + size]
            cur = h[m - iy : m - iy + size, m - ix : m - ix + size]
            snr = rng.uniform(5, 10)
            yield (
                label,
                k,
                (float(d[0]), float(d[1])),
                add_noise(ref, snr=snr, rng=rng),
                add_noise(cur, snr=snr, rng=rng),
            )

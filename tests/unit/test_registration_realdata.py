"""DriftTracker on a real HS-AFM movie: consistency, since no truth exists.

``hsafm_sample_0.asd`` (32 frames, 200×200 px, 0.5 nm/px) drifts by
fractions of a pixel per frame; later frames decorrelate. The tracker's
cumulative position must agree with a direct measurement against frame 0
within the stated uncertainties,
and a known sub-pixel shift applied to a real frame must be recovered.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from afmdrift.io import load_stack
from afmdrift.registration import DriftTracker, RegistrationConfig, measure_drift
from afmdrift.testing import fourier_shift

pytestmark = pytest.mark.realdata

#: 32-px blocks in 64-px windows: 200-px frames hold 49 of them.
SMALL = RegistrationConfig(block_size=32, extended_size=64)


@pytest.fixture
def movie(real_file: Callable[[str], Path]) -> list[np.ndarray]:
    frames = load_stack(str(real_file("hsafm_sample_0.asd")))
    assert frames[0].pixel_size_nm == pytest.approx((0.5, 0.5), rel=0.01)
    return [f.heights_nm for f in frames]


def test_tracker_position_agrees_with_direct_measurement(movie: list[np.ndarray]) -> None:
    tracker = DriftTracker(pixel_size_nm=0.5, config=SMALL)
    tracker.update(movie[0])
    for j in range(1, 13):
        step = tracker.update(movie[j])
        assert step is not None
        assert step.accepted, step.measurement.reason
        direct = measure_drift(movie[0], movie[j], pixel_size_nm=0.5, config=SMALL)
        assert direct.valid, direct.reason
        # Both measure against frame 0, from differently placed windows: they
        # must agree within their stated uncertainties (3 sigma combined).
        sigma_px = np.hypot(step.measurement.sigma_nm, direct.sigma_nm) / 0.5
        tol = max(0.15, 3.0 * float(sigma_px))
        assert step.position_px[0] == pytest.approx(direct.dx_px, abs=tol), j
        assert step.position_px[1] == pytest.approx(direct.dy_px, abs=tol), j


def test_known_shift_of_a_real_frame_is_recovered(movie: list[np.ndarray]) -> None:
    """Fourier-shift a real frame (periodic wrap cut away) by a known amount."""
    img = movie[3] - movie[3].mean()
    d = (2.37, -1.62)
    shifted = fourier_shift(img, dx_px=d[0], dy_px=d[1])
    a, b = img[12:-12, 12:-12], shifted[12:-12, 12:-12]
    r = measure_drift(a, b, pixel_size_nm=0.5, config=SMALL)
    assert r.valid, r.reason
    assert r.dx_px == pytest.approx(d[0], abs=0.05)
    assert r.dy_px == pytest.approx(d[1], abs=0.05)

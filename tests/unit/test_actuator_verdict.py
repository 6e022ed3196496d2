"""The closed loop's check of a re-centre or probe against the frame after it
(``afmdrift.service._closed_loop._verdict``): what each controller would put
where, and what the loop concludes."""

from __future__ import annotations

import pytest

from afmdrift.drivers import Recentre
from afmdrift.service._closed_loop import CHECK_MIN_NM, PROBE_GAIN_TOL, _verdict

Q = (20.0, -15.0)  # 25 nm handed to the frame centre


@pytest.mark.parametrize(
    ("procedure", "e", "expected"),
    [
        # released by off/on: the frame sits on the books, or where a
        # controller that kept the displacement puts it (−q), or elsewhere
        ("release", (1.0, -1.0), "as booked"),
        ("release", (-19.0, 16.0), "kept"),
        ("release", (12.0, 9.0), "mismatch"),
        # ramped out: right whatever off does; anything else is a fault
        ("ramp", (1.0, -1.0), "as booked"),
        ("ramp", (-19.0, 16.0), "mismatch"),
    ],
)
def test_a_re_centre_is_judged_by_what_each_controller_would_show(
    procedure: str, e: tuple[float, float], expected: str
) -> None:
    rc = Recentre(100.0, Q, procedure)  # type: ignore[arg-type]
    verdict, why = _verdict(rc, e, tol=4.0)
    assert verdict == expected
    assert (verdict == "mismatch") == bool(why)


def test_a_displacement_within_the_prediction_error_tells_nothing() -> None:
    rc = Recentre(100.0, (3.0, 0.0), "release")
    assert _verdict(rc, (-1.0, 0.0), tol=4.0)[0] == "undetermined"


@pytest.mark.parametrize(
    ("gain", "expected"),
    [(1.0, "as booked"), (0.9, "as booked"), (0.5, "mismatch"), (-1.0, "mismatch")],
)
def test_a_probe_shows_the_compensation_gain_along_itself(gain: float, expected: str) -> None:
    """A probe q ramped back by a compensation of gain g leaves the frame
    −(1 − g)·q along q; across it, the prediction's lag (here 30 nm along
    the drift, perpendicular to the probe) does not count, and the rolling
    tolerance does not either (a wrong gain inflates it)."""
    q = (0.0, 20.0)
    lag = (30.0, 0.0)
    e = (lag[0] - (1.0 - gain) * q[0], lag[1] - (1.0 - gain) * q[1])
    rc = Recentre(100.0, q, "ramp", "probe")
    verdict, why = _verdict(rc, e, tol=100.0)
    assert verdict == expected
    if expected == "mismatch":
        assert "along the probe" in why
    assert max(PROBE_GAIN_TOL * 20.0, CHECK_MIN_NM) == pytest.approx(5.0)

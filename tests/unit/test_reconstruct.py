"""The continuous offset d(t): the paper's sinc formula and the causal Hermite curve."""

from __future__ import annotations

import functools
import itertools
import json

import numpy as np
import pytest

from afmdrift.errors import InputError
from afmdrift.model import (
    History,
    ModelConfig,
    OffsetCurve,
    build_offset_curve,
    hermite_curve,
    make_predictor,
    reconstruct_offset,
    sinc_reconstruct,
)
from afmdrift.model._synthetic import synthetic_series

PERIOD_S = 256.0


def test_sinc_interpolates_its_samples_exactly() -> None:
    rng = np.random.default_rng(0)
    ti = 100.0 + PERIOD_S * np.arange(20)
    di = rng.normal(0, 10, (20, 2))
    np.testing.assert_allclose(sinc_reconstruct(ti, ti, di, dt_s=PERIOD_S), di, atol=1e-9)


def test_sinc_is_the_published_formula() -> None:
    """d(t) = Σ dᵢ sin(x)/x with x = π(t − tᵢ)/Δt, evaluated by hand at one point."""
    ti = np.array([0.0, 1.0, 2.0])
    di = np.array([[1.0, 0.0], [2.0, 1.0], [-1.0, 3.0]])
    t = 0.4
    x = np.pi * (t - ti)
    expect = (np.sin(x) / x) @ di
    np.testing.assert_allclose(sinc_reconstruct([t], ti, di, dt_s=1.0)[0], expect)


def test_sinc_rings_at_the_window_edge_on_a_ramp() -> None:
    """Documented weakness: a finite sinc sum of a linear ramp leaves the ramp near the edge."""
    ti = PERIOD_S * np.arange(30)
    di = np.column_stack([ti * 0.1, np.zeros_like(ti)])
    t = ti[-1] - 0.5 * PERIOD_S
    err = sinc_reconstruct([t], ti, di, dt_s=PERIOD_S)[0, 0] - t * 0.1
    assert abs(err) > 1.0


@functools.cache
def _curve_sequence(kind: str) -> tuple[list[tuple[float, OffsetCurve]], object]:
    s = synthetic_series(hours=4.0, seed=11, velocity_walk_nm_per_h=2.0)
    pred = make_predictor("kalman")
    curves: list[tuple[float, OffsetCurve]] = []
    prev = None
    for o in s.observations:
        pred.update(o, s.history)
        t_now = o.t_s + 64.0  # the frame completes half a scan after its mid time
        t_obs, xy = pred.observed()
        prev = build_offset_curve(
            "sinc" if kind == "sinc" else "hermite",
            pred,
            s.history,
            t_now_s=t_now,
            measured_t_s=t_obs,
            measured_nm=xy,
            frame_period_s=PERIOD_S,
            previous=prev,
        )
        curves.append((t_now, prev))
    return curves, s


def test_hermite_is_c1_across_publications() -> None:
    curves, _ = _curve_sequence("hermite")
    for (_, a), (t_b, b) in itertools.pairwise(curves):
        np.testing.assert_allclose(b.at([t_b]), a.at([t_b]), atol=1e-9)
        np.testing.assert_allclose(b.derivative([t_b]), a.derivative([t_b]), atol=1e-12)


def test_hermite_does_not_overshoot_at_the_window_edge() -> None:
    """Between knots the curve stays within the knot values when they are monotone,
    including when the predictor's slope would overshoot."""
    curve = hermite_curve(
        [0.0, 256.0, 512.0],
        [[0.0, 0.0], [10.0, 0.0], [11.0, 0.0]],
        [[0.04, 0.0], [0.5, 0.0], [0.5, 0.0]],
    )
    tt = np.linspace(0.0, 512.0, 2001)
    v = curve.at(tt)[:, 0]
    assert v.min() >= -1e-9
    assert v.max() <= 11.0 + 1e-9
    assert np.all(np.diff(v) >= -1e-9)


def test_hermite_beats_sinc_against_true_continuous_drift() -> None:
    """Both reconstructions, used causally as the tip would, compared with the truth."""
    errs = {}
    for kind in ("hermite", "sinc"):
        curves, s = _curve_sequence(kind)
        e = []
        for (t_a, c), (t_b, _) in itertools.pairwise(curves[5:]):
            tt = np.arange(t_a, t_b, 4.0)
            e.append(c.at(tt) - s.truth(tt))  # type: ignore[attr-defined]
        errs[kind] = float(np.mean(np.abs(np.vstack(e))))
    assert errs["hermite"] < 5.0
    assert errs["hermite"] < 0.6 * errs["sinc"]


@pytest.mark.parametrize("kind", ["hermite", "sinc"])
def test_offset_curve_json_round_trip(kind: str) -> None:
    curves, _ = _curve_sequence(kind)
    c = curves[-1][1]
    back = OffsetCurve.from_dict(json.loads(json.dumps(c.to_dict())))
    tt = np.linspace(c.t_valid_s[0] - 50, c.t_valid_s[1] + 50, 77)
    np.testing.assert_array_equal(back.at(tt), c.at(tt))
    assert back.t_valid_s == c.t_valid_s


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"format": "other"}, "expected format"),
        ({"kind": "spline"}, "kind must be"),
        ({"knot_nm": [[0.0, 1.0]]}, "knot times"),
        ({"t_valid_s": None}, "malformed"),
    ],
)
def test_offset_curve_from_bad_dict_names_the_field(patch: dict, message: str) -> None:
    d = hermite_curve([0.0, 1.0], [[0, 0], [1, 1]], [[1, 1], [1, 1]]).to_dict()
    d.update(patch)
    with pytest.raises(InputError, match=message):
        OffsetCurve.from_dict(d)


def test_reconstruct_offset_follows_the_config() -> None:
    h = History()
    p = make_predictor("constant_velocity")
    from afmdrift.model import Observation
    from afmdrift.records import ScanDirection

    for i in range(4):
        p.update(Observation(PERIOD_S * i, 2.0 * i, -1.0 * i, 0.1, ScanDirection.UP, i), h)
    for kind in ("hermite", "sinc"):
        c = reconstruct_offset(
            p, h, config=ModelConfig(reconstruction=kind), t_now_s=3 * PERIOD_S + 64
        )  # type: ignore[arg-type]
        assert c.kind == kind
    c = reconstruct_offset(p, h, config=ModelConfig(), t_now_s=3 * PERIOD_S + 64)
    t = 3 * PERIOD_S + 200.0
    np.testing.assert_allclose(c.at([t])[0], [2.0 * t / PERIOD_S, -t / PERIOD_S], atol=1e-9)
    with pytest.raises(ValueError, match="no observations"):
        reconstruct_offset(make_predictor("kalman"), h, config=ModelConfig(), t_now_s=0.0)


def test_blended_hermite_is_c1_and_reaches_the_new_prediction() -> None:
    """With blend_fraction the hand-over to a new prediction takes a tenth of a frame,
    and the curve still starts from the previous curve's value and slope."""
    s = synthetic_series(hours=2.0, seed=4, velocity_walk_nm_per_h=3.0)
    pred = make_predictor("kalman")
    cfg = ModelConfig(blend_fraction=0.1)
    prev = None
    for o in s.observations:
        pred.update(o, s.history)
        t_now = o.t_s + 64.0
        cur = reconstruct_offset(pred, s.history, config=cfg, t_now_s=t_now, previous=prev)
        if prev is not None:
            np.testing.assert_allclose(cur.at([t_now]), prev.at([t_now]), atol=1e-9)
            np.testing.assert_allclose(
                cur.derivative([t_now]), prev.derivative([t_now]), atol=1e-12
            )
        t_hand = t_now + 0.1 * PERIOD_S
        np.testing.assert_allclose(
            cur.at([t_hand]), pred.predict([t_hand], s.history).mean_nm, atol=1e-9
        )
        prev = cur

"""d(t) across a change of the model: the hand-over curve of
:meth:`FramePipeline.plan_handover`, against its own ground truth.

The drift is a slow trend plus a cycle; a model with the trend alone
predicts it far from one that also has the cycle, so switching from the one
to the other would step d(t) by several nm. The hand-over curve starts at the
published curve's value and slope, reaches the new prediction, and no two
samples of the stream differ by more than the bound.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmdrift.config import AfmdriftConfig, parse_config
from afmdrift.model import Observation, make_predictor
from afmdrift.pipeline import MIN_HANDOVER_STEP_NM, FramePipeline, largest_step_nm
from afmdrift.records import ScanDirection

PERIOD_S = 600.0


def _config(terms: list[str], reconstruction: str = "hermite") -> AfmdriftConfig:
    return parse_config(
        {
            "model": {
                "predictor": "physics",
                "reconstruction": reconstruction,
                "physics": {"terms": terms, "residual": "none"},
            }
        }
    )


def _pipeline(reconstruction: str = "hermite") -> FramePipeline:
    """A pipeline whose trend-only model has seen 40 frames of a trend plus a
    cycle (amplitude 8 nm, period 600 s) and published its curve."""
    pipeline = FramePipeline(config=_config(["trend"], reconstruction))
    rng = np.random.default_rng(3)
    for k in range(40):
        t = 20.0 * k
        x = 0.01 * t + 8.0 * math.sin(2 * math.pi * t / PERIOD_S) + rng.normal(0, 0.1)
        y = -0.005 * t + 6.0 * math.cos(2 * math.pi * t / PERIOD_S) + rng.normal(0, 0.1)
        pipeline.observations.append(Observation(t, x, y, 0.1, direction=ScanDirection.UP, frame=k))
    pipeline.reload_model(pipeline.predictor)
    assert pipeline.curve is not None
    return pipeline


def test_handover_is_continuous_reaches_the_new_model_and_keeps_the_bound() -> None:
    pipeline = _pipeline()
    old = pipeline.curve
    assert old is not None
    new_model = _config(["trend", f"periodic:period_s={PERIOD_S:g}"]).model
    predictor = make_predictor("physics", new_model)
    pipeline.refit(predictor)
    t_now, interval = 790.0, 0.02
    plan = pipeline.plan_handover(predictor, t_now_s=t_now, sample_interval_s=interval)
    assert plan.curve is not None
    target = predictor.predict_drift([t_now], pipeline.history)
    gap = float(np.hypot(*(target.mean_nm[0] - old.at([t_now])[0])))
    assert plan.bound_nm >= MIN_HANDOVER_STEP_NM
    assert gap > 5 * plan.bound_nm  # switching at once would step d(t) by the gap
    # continuous in value and slope with the published curve at the change
    np.testing.assert_allclose(plan.curve.at([t_now]), old.at([t_now]), atol=1e-9)
    np.testing.assert_allclose(plan.curve.derivative([t_now]), old.derivative([t_now]), atol=1e-9)
    # every step of a stream sampled every interval keeps the bound, past the hand-over too
    t = np.arange(t_now, plan.until_s + 20.0, interval / 7)
    steps = plan.curve.at(t + interval) - plan.curve.at(t)
    assert float(np.max(np.hypot(steps[:, 0], steps[:, 1]))) <= plan.bound_nm
    assert plan.step_nm == pytest.approx(
        largest_step_nm(plan.curve, t_now, plan.until_s + 2 * interval, interval)
    )
    # and it ends on the new model's prediction
    end = predictor.predict_drift([plan.until_s], pipeline.history).mean_nm[0]
    np.testing.assert_allclose(plan.curve.at([plan.until_s])[0], end, atol=1e-6)
    # nothing changed until the plan is used
    assert pipeline.curve is old
    pipeline.use_model(predictor, plan)
    assert pipeline.curve is plan.curve
    assert pipeline.predictor is predictor


def test_a_larger_interval_hands_over_more_slowly() -> None:
    pipeline = _pipeline()
    predictor = make_predictor("physics", _config(["trend", "periodic:period_s=600"]).model)
    pipeline.refit(predictor)
    fast = pipeline.plan_handover(predictor, t_now_s=790.0, sample_interval_s=0.1)
    slow = pipeline.plan_handover(predictor, t_now_s=790.0, sample_interval_s=1.0)
    assert fast.curve is not None
    assert slow.curve is not None
    assert slow.until_s - 790.0 > 2 * (fast.until_s - 790.0)
    for plan in (fast, slow):
        assert plan.step_nm <= plan.bound_nm


def test_no_handover_without_a_hermite_curve() -> None:
    """The sinc curve does not start from the previous one: nothing to plan."""
    pipeline = _pipeline(reconstruction="sinc")
    predictor = make_predictor("physics", _config(["trend", "periodic:period_s=600"]).model)
    plan = pipeline.plan_handover(predictor, t_now_s=790.0, sample_interval_s=0.02)
    assert plan.curve is None


def test_with_a_lead_the_curve_is_the_published_one_until_it_hands_over() -> None:
    """Guards against a stream that takes the new curve up late (after the
    store's commit, at a simulator's speed-up) entering the blend part-way:
    with a lead the new curve equals the published one up to the lead's end,
    so wherever before it the stream switches, it sees no step."""
    pipeline = _pipeline()
    old = pipeline.curve
    assert old is not None
    predictor = make_predictor("physics", _config(["trend", "periodic:period_s=600"]).model)
    pipeline.refit(predictor)
    t_now, interval, lead = 790.0, 0.02, 45.0
    plan = pipeline.plan_handover(predictor, t_now_s=t_now, sample_interval_s=interval, lead_s=lead)
    assert plan.curve is not None
    before = np.linspace(t_now, t_now + lead, 400)
    np.testing.assert_allclose(plan.curve.at(before), old.at(before), atol=1e-9)
    np.testing.assert_allclose(plan.curve.derivative(before), old.derivative(before), atol=1e-9)
    assert plan.until_s > t_now + lead
    t = np.arange(t_now, plan.until_s + 20.0, interval / 7)
    steps = plan.curve.at(t + interval) - plan.curve.at(t)
    assert float(np.max(np.hypot(steps[:, 0], steps[:, 1]))) <= plan.bound_nm
    end = predictor.predict_drift([plan.until_s], pipeline.history).mean_nm[0]
    np.testing.assert_allclose(plan.curve.at([plan.until_s])[0], end, atol=1e-6)

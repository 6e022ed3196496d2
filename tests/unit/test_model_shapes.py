"""Drift-shape term specs (``periodic:``, ``jump:``, ``rate_change:``): what a user pastes.

The design of each shape, the places that accept a spec, the errors of a
malformed one, and a jump term fitted online.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.config import PhysicsConfig
from afmdrift.errors import ConfigError
from afmdrift.model import (
    DriftShape,
    History,
    Observation,
    PhysicsPredictor,
    make_term,
    parse_term_spec,
    resolve_terms,
)


def _design(spec: str, t: np.ndarray) -> np.ndarray:
    term = make_term(spec)
    return term.design(t, History(), scan_sign=np.ones(t.size), params={}, axis=0)


def test_drift_shape_specs_build_a_cycle_a_step_and_a_kink() -> None:
    t = np.array([0.0, 450.0, 900.0, 1800.0, 3600.0])
    cyc = _design("periodic:period_s=1800", t)
    np.testing.assert_allclose(cyc[:, 0], np.sin(2 * np.pi * t / 1800.0), atol=1e-12)
    np.testing.assert_allclose(cyc[:, 1], np.cos(2 * np.pi * t / 1800.0), atol=1e-12)
    np.testing.assert_array_equal(_design("jump:t_s=1000", t)[:, 0], [0, 0, 0, 1, 1])
    np.testing.assert_allclose(_design("rate_change:t_s=900", t)[:, 0], [0, 0, 0, 0.25, 0.75])
    cls = parse_term_spec("jump:t_s=19200#2")
    assert issubclass(cls, DriftShape)
    assert cls.name == "jump:t_s=19200#2"
    assert cls.coefficient_units == ("step_nm",)
    assert parse_term_spec("periodic:period_s=1200..2400").nonlinear_params[0].name == "period_s"


def test_the_pasted_terms_are_accepted_where_a_term_name_is() -> None:
    terms = ["trend", "periodic:period_s=1860", "jump:t_s=19200", "rate_change:t_s=7200"]
    assert len(resolve_terms(terms)) == 4
    PhysicsPredictor(PhysicsConfig(terms=terms))


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("jump:19200", "expected 'jump:t_s=<value in s>'"),
        ("jump:t_s=later", "needs a number"),
        ("periodic:t_s=100", "expected 'periodic:period_s=<value in s>'"),
        ("rate_change:t_s=-5", "must be positive"),
        ("jump:t_s=100:each", "expected 'jump:t_s=<value in s>'"),
    ],
)
def test_a_malformed_drift_shape_names_what_is_wrong(spec: str, says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        resolve_terms(["trend", spec])


def test_a_fitted_jump_term_learns_the_step_online() -> None:
    """With the jump's time given, the model predicts the frames after it
    without the step in them: one frame is surprised, not the rest."""
    p = PhysicsPredictor(PhysicsConfig(terms=["trend", "jump:t_s=3000"], residual="none"))
    errors = []
    for k in range(40):
        t = 150.0 + 200.0 * k
        x = 0.01 * t + (12.0 if t > 3000.0 else 0.0)
        obs = Observation(t_s=t, x_nm=x, y_nm=-x, sigma_nm=0.1)
        if k >= 2:
            errors.append(abs(float(p.predict([t], History()).mean_nm[0, 0]) - x))
        p.update(obs, History())
    assert max(errors[16:]) < 1e-6  # frames 18.. (the jump is between 14 and 15)
    assert p.coefficients()["jump:t_s=3000"]["x"][0] == pytest.approx(12.0, abs=1e-6)

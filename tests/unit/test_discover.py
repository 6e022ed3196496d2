"""What diagnose finds in the drift itself: a cycle, a jump, and nothing on a control.

The sessions are built here from the equations (a trend, a random walk,
noise, and one shape nothing logged drives), independently of the simulator
and of the second generator; ``benchmarks/bench_discover.py`` measures the
rates over both generators and the shared logs.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics import DiagnoseOptions, RunData, diagnose, diagnosis_text
from afmdrift.diagnostics._candidates import CandidateResult
from afmdrift.diagnostics._finding import plain_finding
from afmdrift.diagnostics._text import cv_change
from afmdrift.records import Event, EventKind


def _session(
    shape: str, *, seed: int, n: int = 110, period_s: float = 240.0
) -> tuple[RunData, float]:
    """A drift log of ``n`` frames: trend, random walk, noise, and ``shape``;
    returns the data and where the shape is (its time or period, s)."""
    rng = np.random.default_rng(seed)
    t = 60.0 + period_s * np.arange(n)
    walk = np.cumsum(rng.normal(0.0, 0.12, (n, 2)), axis=0)
    xy = np.outer(t, [0.02, -0.015]) + walk + rng.normal(0.0, 0.1, (n, 2))
    where = math.nan
    if shape == "cycle":
        where = 1800.0
        xy += np.outer(3.0 * np.sin(2 * np.pi * t / where + 0.7), [0.8, 0.6])
    elif shape == "jump":
        where = float(t[70] - 0.5 * period_s)
        xy += np.outer(t > where, [-9.0, 11.0])
    xy -= xy[0]
    data = RunData.from_arrays(
        t_s=t, xy_nm=xy, t_end_s=t + 60.0, events=[Event(t_s=1.0, kind=EventKind.POWER_ON)]
    )
    return data, where


def _diagnosed(shape: str, seed: int) -> tuple[dict, float, float]:  # type: ignore[type-arg]
    data, where = _session(shape, seed=seed)
    dg = diagnose(data, PhysicsConfig(terms=["trend"]), options=DiagnoseOptions())
    return dg.to_json(), where, float(np.median(np.diff(data.t_s)))


def test_an_unlogged_cycle_is_found_with_its_period_and_the_term_to_paste() -> None:
    j, period, _ = _diagnosed("cycle", seed=3)
    top = j["candidates"][0]
    assert top["significant"]
    assert top["family"] == "discovered"
    assert top["discovered"]["kind"] == "periodic"
    assert top["discovered"]["period_s"] == pytest.approx(period, rel=0.05)
    assert top["term"] == f"periodic:period_s={top['discovered']['period_s']:.0f}"
    assert j["after"]["rmse_drop"] > 0.3
    assert j["plain_finding"].startswith("Missing: a 30-min cycle of 3")
    assert "no logged channel follows: an air handler or a thermostat?" in j["plain_finding"]


def test_an_unlogged_jump_is_found_within_a_frame() -> None:
    j, t_jump, frame_s = _diagnosed("jump", seed=4)
    jumps = [c for c in j["candidates"] if (c["discovered"] or {}).get("kind") == "jump"]
    assert jumps[0]["significant"]
    assert abs(jumps[0]["discovered"]["t_s"] - t_jump) <= frame_s
    assert jumps[0]["discovered"]["step_nm"] == pytest.approx([-9.0, 11.0], abs=1.0)


def test_a_control_has_no_discovered_candidate_and_says_so_plainly() -> None:
    j, _, _ = _diagnosed("none", seed=5)
    assert not any(c["significant"] for c in j["candidates"])
    assert j["plain_finding"].startswith("Nothing is missing that these data can show")
    text = diagnosis_text(j)
    assert text.splitlines()[0] == j["plain_finding"]


#: The CLI's first paragraph of the three sessions above, end to end (the data
#: built, diagnosed, said): what a user reads first.
GOLDEN_FIRST_PARAGRAPH = {
    ("cycle", 3): (
        "Missing: a 30-min cycle of 3 nm that no logged channel follows: an air handler "
        "or a thermostat? Log the room temperature near the instrument, or add "
        "`periodic:period_s=1806` to [model.physics] terms; with it the one-step error "
        "falls from 1.73 to 0.30 nm RMS (83 % lower)."
    ),
    ("jump", 4): (
        "Missing: a jump of (\u22129, +11) nm at 4 h 39 min that no logged event explains: "
        "a slip or a tip change? Add `jump:t_s=16740` to [model.physics] terms (or log tip "
        "changes and slips as events); with it the one-step error on the frames after it "
        "falls from 0.44 to 0.26 nm RMS (40 % lower)."
    ),
    ("none", 5): (
        "Nothing is missing that these data can show: none of the 7 effects, logged "
        "responses and drift shapes tested improves the model's predictions enough to "
        "matter. Keep the model as it is (its one-step error is 0.26 nm RMS)."
    ),
}


@pytest.mark.parametrize(("shape", "seed"), sorted(GOLDEN_FIRST_PARAGRAPH))
def test_golden_first_paragraph_end_to_end(shape: str, seed: int) -> None:
    """Exact, but for where a jump is placed: within one frame of the truth
    (checked), the frame itself borderline between two on this session
    (16740 and 16795 s, one frame apart, on two fresh installs of the
    project, whose dependencies are pinned only for torch), so its time is
    compared as a placeholder."""
    j, t_jump, frame_s = _diagnosed(shape, seed)
    first = diagnosis_text(j).split("\n\n")[0]
    golden = GOLDEN_FIRST_PARAGRAPH[(shape, seed)]
    assert _jump_placed(first, t_jump, frame_s) == _jump_placed(golden, t_jump, frame_s)
    assert _jump_placed(j["plain_finding"], t_jump, frame_s) == _jump_placed(
        golden, t_jump, frame_s
    )


def _jump_placed(text: str, t_jump: float, frame_s: float) -> str:
    """``text`` with a jump's time (``jump:t_s=N`` and "at H h M min") replaced
    by placeholders, after checking it is within one frame of ``t_jump``."""
    m = re.search(r"jump:t_s=(\d+)", text)
    if m is None:
        return text
    t_s = int(m[1])
    assert abs(t_s - t_jump) <= frame_s, (t_s, t_jump, frame_s)
    text = text.replace(m[0], "jump:t_s=<t>")
    return re.sub(r"at \d+ h \d+ min", "at <h min>", text)


def _found(kind: str, value: dict, params: dict[str, float]) -> CandidateResult:  # type: ignore[type-arg]
    spec = {"periodic": "periodic:period_s=", "jump": "jump:t_s="}[kind]
    where = value.get("period_s", value.get("t_s"))
    return CandidateResult(
        effect=f"{spec}{where:.0f}",
        testable=True,
        significant=True,
        driver={"drift_shape": kind},
        discovered={"kind": kind, **value},
        params=params,
    )


def test_golden_plain_paragraph_of_a_cycle() -> None:
    c = _found("periodic", {"period_s": 1860.0, "amplitude_nm": [3.36, 2.52]}, {})
    text = plain_finding(c, [c], {"rmse_nm": 2.25}, {"rmse_nm": 0.9})
    assert text == (
        "Missing: a 31-min cycle of 4.2 nm that no logged channel follows: an air handler "
        "or a thermostat? Log the room temperature near the instrument, or add "
        "`periodic:period_s=1860` to [model.physics] terms; with it the one-step error "
        "falls from 2.25 to 0.90 nm RMS (60 % lower)."
    )


def test_golden_plain_paragraph_of_a_jump() -> None:
    c = _found("jump", {"t_s": 19200.0, "step_nm": [-136.2, 168.4]}, {})
    c.rmse_after_kind, c.rmse_base_nm, c.rmse_after_nm = "replayed", 2.10, 0.42
    text = plain_finding(c, [c], {"rmse_nm": 14.1}, {"rmse_nm": 9.8})
    assert text == (
        "Missing: a jump of (\u2212136, +168) nm at 5 h 20 min that no logged event explains: "
        "a slip or a tip change? Add `jump:t_s=19200` to [model.physics] terms (or log tip "
        "changes and slips as events); with it the one-step error on the frames after it "
        "falls from 2.10 to 0.42 nm RMS (80 % lower)."
    )


def test_golden_plain_paragraph_of_a_control() -> None:
    results = [CandidateResult(effect=f"e{k}", testable=True) for k in range(7)]
    text = plain_finding(None, results, {"rmse_nm": 0.61}, None)
    assert text == (
        "Nothing is missing that these data can show: none of the 7 effects, logged "
        "responses and drift shapes tested improves the model's predictions enough to "
        "matter. Keep the model as it is (its one-step error is 0.61 nm RMS)."
    )


def test_a_meaningless_change_percentage_is_shown_as_what_it_is() -> None:
    """Regression guard: a term whose cross-validated error blew up read
    ``+509038%`` in the CV column; it reads ``unstable``."""
    assert cv_change({"cv_drop": -5090.38}) == "unstable"
    assert cv_change({"cv_drop": 0.25}) == "-25%"
    assert cv_change({"cv_drop": None}) == "-"

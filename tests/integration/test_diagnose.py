"""``afmdrift diagnose`` end to end on simulated sessions with one hidden effect.

Each scenario in ``config/scenarios/hidden`` puts one drift effect in the
simulated instrument that the model is not given (see the comment at the top of
each file); ``control.toml`` has every effect modelled. Sessions are recorded,
replayed through the service pipeline (registration included) and diagnosed.

Three scenarios hide effects that no library term names (``OUTSIDE``: a
pressure channel through a lag, a stage thermometer with a fast and a slow
path, settling after a lab's own ``stage_move`` events); diagnose must name
their driver through the generic ``channel:``/``event:`` terms.
``control_distractors.toml`` adds logged channels and events that move nothing.

Each session takes about half a minute of CPU to diagnose, so the sweeps are
not part of ``make test`` (on a busy two-core laptop the default sweep alone
passed the per-test timeout): ``-m soak`` runs them, the default sweep (every
library effect and ``stage_move`` with one seed, the two controls with two) and
the full 10-seed sweep with the acceptance criteria, and
``benchmarks/bench_diagnose.py`` reports the same figures over this simulator,
a second generator and the shared validation logs. ``make test`` keeps the
end-to-end CLI case below (one session of 50 frames, its finding and its
report). The acceptance criteria of the full sweep: the hidden effect (or its
driver) ranked first and significant, with adding it cutting the one-step RMS
error by at least 30 %, in
at least 8 of 10 seeds, and each control raises no significant finding in at
least 9 of 10 seeds.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest

from afmdrift.config import AfmdriftConfig
from afmdrift.registration import RegistrationConfig

HIDDEN = Path(__file__).resolve().parents[2] / "config" / "scenarios" / "hidden"

#: Model terms each scenario is diagnosed with (None: the default model).
CASES: dict[str, list[str] | None] = {
    "thermal_lag": ["trend", "warmup", "creep", "scan_direction"],
    "humidity": None,
    "creep": ["trend", "warmup", "thermal_lag", "scan_direction"],
    "warmup": ["trend", "thermal_lag", "creep", "scan_direction"],
    "scan_direction": ["trend", "warmup", "thermal_lag", "creep"],
    "control": None,
    "pressure": None,
    "stage_thermometer": None,
    "stage_move": None,
    "control_distractors": None,
}

#: Effects outside the library: the driver the top candidate must name.
OUTSIDE: dict[str, tuple[str, str]] = {
    "pressure": ("channel", "pressure_hpa"),
    "stage_thermometer": ("channel", "stage_c"),
    "stage_move": ("event_kind", "stage_move"),
}
CONTROLS = ("control", "control_distractors")
LIBRARY_CASES = [c for c in CASES if c not in OUTSIDE and c not in CONTROLS]

#: Registration for the small 128×128 px frames of the hidden scenarios.
SMALL_FRAMES_TOML = "[registration]\nblock_size = 32\nextended_size = 96\n"


def small_frames_config() -> AfmdriftConfig:
    return AfmdriftConfig(registration=RegistrationConfig(block_size=32, extended_size=96))


@dataclass(frozen=True)
class Outcome:
    case: str
    seed: int
    top: str
    top_driver: str | None
    top_significant: bool
    any_significant: bool
    rmse_nm: float
    rmse_after_nm: float | None
    wall_s: float


def run_case(case: str, seed: int, workdir: str) -> Outcome:
    """Record the hidden-effect session, replay it and diagnose it."""
    import time

    from afmdrift.diagnostics._run import diagnose_path
    from afmdrift.drivers.sim._record import record_session

    started = time.perf_counter()
    session = Path(workdir) / f"{case}-{seed}"
    record_session(HIDDEN / f"{case}.toml", session, seed=seed)
    dg, _ = diagnose_path(session, config=small_frames_config(), effects=CASES[case])
    j = dg.to_json()
    top = j["candidates"][0]
    return Outcome(
        case=case,
        seed=seed,
        top=top["effect"],
        top_driver=top["params"].get("channel") or top["params"].get("event_kind"),
        top_significant=bool(top["significant"]),
        any_significant=any(c["significant"] for c in j["candidates"]),
        rmse_nm=float(j["rmse_nm"]),
        rmse_after_nm=None if j["after"] is None else float(j["after"]["rmse_nm"]),
        wall_s=time.perf_counter() - started,
    )


def sweep(cases: list[str], seeds: list[int], workdir: Path) -> dict[tuple[str, int], Outcome]:
    """All (case, seed) runs on at most two processes."""
    jobs = [(c, s) for c in cases for s in seeds]
    with ProcessPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
        futures = {job: pool.submit(run_case, job[0], job[1], str(workdir)) for job in jobs}
        return {job: f.result() for job, f in futures.items()}


DEFAULT_SEEDS = [101]
CONTROL_SEEDS = [101, 102]

#: Out-of-library cases of the default run (stage_move also carries a lab's own
#: event kind from the simulator through the session, replay and run store).
DEFAULT_OUTSIDE = ["stage_move"]


@pytest.fixture(scope="module")
def default_sweep(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, int], Outcome]:
    work = tmp_path_factory.mktemp("hidden")
    out = sweep([*LIBRARY_CASES, *DEFAULT_OUTSIDE], DEFAULT_SEEDS, work)
    out.update(sweep(list(CONTROLS), CONTROL_SEEDS, work))
    return out


@pytest.mark.soak
@pytest.mark.parametrize("case", LIBRARY_CASES)
def test_hidden_effect_is_found_and_adding_it_cuts_the_error(
    case: str, default_sweep: dict[tuple[str, int], Outcome]
) -> None:
    for seed in DEFAULT_SEEDS:
        o = default_sweep[(case, seed)]
        assert o.top == case, o
        assert o.top_significant, o
        assert o.rmse_after_nm is not None
        assert o.rmse_after_nm <= 0.7 * o.rmse_nm, o


@pytest.mark.soak
@pytest.mark.parametrize("case", DEFAULT_OUTSIDE)
def test_effect_outside_the_library_is_named_by_its_driver(
    case: str, default_sweep: dict[tuple[str, int], Outcome]
) -> None:
    for seed in DEFAULT_SEEDS:
        o = default_sweep[(case, seed)]
        assert o.top_driver == OUTSIDE[case][1], o
        assert o.top_significant, o
        assert o.rmse_after_nm is not None
        assert o.rmse_after_nm <= 0.7 * o.rmse_nm, o


@pytest.mark.soak
@pytest.mark.parametrize("case", CONTROLS)
def test_control_session_raises_no_false_alarm(
    case: str, default_sweep: dict[tuple[str, int], Outcome]
) -> None:
    """Regression guard: a complete model must not be told an effect is missing, also
    when the lab logs channels and event kinds that do not move the sample."""
    for seed in CONTROL_SEEDS:
        o = default_sweep[(case, seed)]
        assert not o.any_significant, o


@pytest.mark.slow
def test_cli_diagnose_session_prints_json_and_writes_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from afmdrift.cli import main
    from afmdrift.drivers.sim._record import record_session

    session = tmp_path / "session"
    record_session(HIDDEN / "scan_direction.toml", session, seed=7, frames=50)
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_FRAMES_TOML, encoding="utf-8")
    report = tmp_path / "report.html"
    run_dir = tmp_path / "run"
    code = main(
        [
            "diagnose",
            str(session),
            "--config",
            str(cfg),
            "--effects",
            "trend,thermal_lag,creep",
            "--json",
            "--report",
            str(report),
            "--run-dir",
            str(run_dir),
        ]
    )
    assert code == 0
    j = json.loads(capsys.readouterr().out)
    assert j["model_effects"] == ["trend", "thermal_lag", "creep"]
    top = j["candidates"][0]
    assert top["effect"] == "scan_direction"
    assert top["significant"]
    assert top["params"]["bias_nm_x"] == pytest.approx(3.0, abs=0.6)
    assert 'terms = ["trend", "thermal_lag", "creep", "scan_direction"]' in j["config"]
    assert j["after"]["rmse_nm"] < j["rmse_nm"]
    assert report.stat().st_size > 10_000
    assert (run_dir / "measurements.csv").is_file()

    # The replayed run directory can be diagnosed again without a new replay,
    # now with the effect added: nothing is missing any more.
    code = main(
        [
            "diagnose",
            str(run_dir),
            "--config",
            str(cfg),
            "--effects",
            "trend,thermal_lag,creep,scan_direction",
            "--session",
            str(session),
            "--json",
        ]
    )
    assert code == 0
    j2 = json.loads(capsys.readouterr().out)
    assert not any(c["significant"] for c in j2["candidates"])
    assert j2["rmse_nm"] == pytest.approx(j["after"]["rmse_nm"], rel=1e-6)


def test_cli_diagnose_rejects_a_path_that_is_neither(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from afmdrift.cli import main

    assert main(["diagnose", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "neither a run directory" in err


@pytest.mark.soak
@pytest.mark.parametrize("case", list(CASES))
def test_full_ten_seed_sweep(case: str, tmp_path: Path) -> None:
    seeds = list(range(1, 11))
    res = sweep([case], seeds, tmp_path)
    outcomes = [res[(case, s)] for s in seeds]
    summary = [
        (o.seed, o.top, o.top_significant, round(o.rmse_nm, 2), o.rmse_after_nm) for o in outcomes
    ]
    if case in CONTROLS:
        alarms = sum(o.any_significant for o in outcomes)
        assert alarms <= 1, summary
        return
    if case in OUTSIDE:
        found = [o for o in outcomes if o.top_driver == OUTSIDE[case][1] and o.top_significant]
    else:
        found = [o for o in outcomes if o.top == case and o.top_significant]
    # Found and adding it cuts the one-step RMS error by at least 30 %, in 8 of 10 seeds.
    met = [o for o in found if o.rmse_after_nm is not None and o.rmse_after_nm <= 0.7 * o.rmse_nm]
    assert len(met) >= 8, summary

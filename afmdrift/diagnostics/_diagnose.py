"""Model against measurement: compare, locate failures, find the missing effect.

:func:`diagnose` takes the per-frame measurements of a run (:class:`RunData`)
and a physics model (a list of effect terms) and

1. **compares**: re-runs the model online over the measured positions exactly
   as the drift service does (fit on the frames so far, predict the next
   frame, with the channels and events logged up to the end of that frame;
   :mod:`afmdrift.diagnostics._model_run`) and summarises the one-step
   errors; where the session has the true drift, also the error of the
   model's continuous prediction between frames;
2. **locates failures**: episodes of large or persistently biased errors,
   each linked to what was logged then; Ljung–Box, periodogram, CUSUM and
   the up/down frame difference (:mod:`afmdrift.diagnostics._stats`);
3. **finds the missing effect**: tests every library term not in the model,
   the generic response to every logged channel and event kind
   (:mod:`afmdrift.diagnostics._candidates`) and the shapes read from the
   drift itself, a cycle, a jump, a change of rate
   (:mod:`afmdrift.diagnostics._discover`), ranks them, and for the top
   candidates re-runs the model online with the term added to measure the
   new one-step error ("add it and watch the error fall";
   :mod:`afmdrift.diagnostics._ranking`); the re-runs are independent and run
   side by side (:class:`afmdrift.runs.TaskPool`: this machine's cores, or the
   Dask cluster of ``afmdrift batch``);
4. **says it**: the patterns of the errors and the finding in plain language
   (:mod:`afmdrift.diagnostics._finding`), in a :class:`Diagnosis`.

The statistics and the JSON object are documented in ``docs/diagnostics.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._diagnosis import DiagnoseOptions, Diagnosis
from afmdrift.diagnostics._finding import (
    error_patterns,
    finding_text,
    plain_finding,
    with_jump_caution,
)
from afmdrift.diagnostics._model_run import ModelRun, model_design, run_from_store, run_model
from afmdrift.diagnostics._ranking import (
    candidate_evidence,
    mark_indistinguishable,
    rank_candidates,
    verify_online,
)
from afmdrift.diagnostics._regression import MIN_FITTED_POINTS
from afmdrift.diagnostics._stats import (
    error_summary,
    find_episodes,
    ljung_box,
    lomb_scargle,
    up_down_difference,
)
from afmdrift.errors import ConfigError, TooFewFramesError
from afmdrift.model import EffectTerm, available_terms, resolve_terms, warm_up_effects
from afmdrift.runs import TaskPool

__all__ = ["MIN_DIAGNOSE_FRAMES", "DiagnoseOptions", "Diagnosis", "diagnose"]

#: The fewest frames that fed the model a diagnosis is made on: the candidate
#: tests fit :data:`~afmdrift.diagnostics._regression.MIN_FITTED_POINTS`
#: AR(1) quasi-differences, one fewer than the frames. With fewer, no
#: candidate can be tested, and "nothing is missing" would be said over no
#: test at all.
MIN_DIAGNOSE_FRAMES = MIN_FITTED_POINTS + 1


def diagnose(
    data: RunData,
    physics: PhysicsConfig,
    *,
    effects: Sequence[str] | None = None,
    options: DiagnoseOptions | None = None,
) -> Diagnosis:
    """Compare the model with the measurements, locate failures, test missing effects.

    Parameters
    ----------
    data : RunData
        Per-frame measurements with channels and events.
    physics : PhysicsConfig
        The model configuration (``[model.physics]``).
    effects : sequence of str, optional
        Replace the configured terms (``--effects``).
    options : DiagnoseOptions

    Raises
    ------
    ConfigError
        Unknown or duplicate effect names.
    TooFewFramesError
        Fewer than :data:`MIN_DIAGNOSE_FRAMES` frames fed the model.
    """
    fed = int(np.count_nonzero(data.fed))
    if fed < MIN_DIAGNOSE_FRAMES:
        where = data.session_dir or data.run_dir
        raise TooFewFramesError(
            fed,
            MIN_DIAGNOSE_FRAMES,
            where="" if where is None else str(where),
            why=f"the candidate tests fit {MIN_FITTED_POINTS} frame-to-frame steps",
        )
    options = options or DiagnoseOptions()
    physics, known = _chosen_physics(physics, effects)
    # The re-runs' processes start now and import while the model runs here.
    with TaskPool(options.workers, warm=warm_up_effects) as pool:
        return _diagnose(data, physics, known, options, pool)


def _diagnose(
    data: RunData,
    physics: PhysicsConfig,
    known: dict[str, type[EffectTerm]],
    options: DiagnoseOptions,
    pool: TaskPool,
) -> Diagnosis:
    """:func:`diagnose` with its model and known terms chosen, re-runs on ``pool``."""
    run = run_from_store(data, physics) or run_model(data, physics)
    burn = min(options.burn_in_frames, max(run.t_s.size - 8, 0))
    summary = run.summary(burn)
    e = run.errors_nm
    lb, pg = _whiteness(run, burn)
    failures = find_episodes(
        data, run.t_s[burn:], run.frames[burn:], e[burn:], run.scan_sign[burn:]
    )
    up_down = up_down_difference(e[burn:], run.scan_sign[burn:])
    truth_summary = error_summary(run.truth_errors_nm) if run.truth_errors_nm is not None else None

    design = model_design(run)
    results, n_tests = candidate_evidence(design, run.history, known, physics, options)
    runs = verify_online(
        results, data, physics, base=run, burn=burn, rmse0_nm=summary["rmse_nm"],
        options=options, pool=pool,
    )  # fmt: skip
    step_s = float(np.median(np.diff(run.t_s))) if run.t_s.size > 1 else math.inf
    rank_candidates(results, options.thresholds, frame_period_s=step_s)
    mark_indistinguishable(results, runs, run, burn, options.thresholds.alpha)
    top = results[0] if results and results[0].significant else None
    after: ModelRun | None = None
    after_summary = None
    if top is not None and top.effect in runs:
        after, after_summary = runs[top.effect]
    finding, config_terms = finding_text(
        top, results, physics, summary, after_summary, n_tests, options
    )
    finding = with_jump_caution(finding, run)
    plain = plain_finding(top, results, summary, after_summary, options.thresholds)
    return Diagnosis(
        model_effects=list(physics.terms),
        active_effects=list(run.predictor.active),
        run=run,
        burn_in_frames=burn,
        summary=summary,
        truth_summary=truth_summary,
        ljung_box=lb,
        periodogram=pg,
        up_down=up_down,
        failures=failures,
        patterns=error_patterns(data, run, burn, lb, pg, up_down),
        candidates=results,
        n_tests=n_tests,
        thresholds=options.thresholds,
        phi=[float(v) for v in design.phi],
        finding=finding,
        plain=plain,
        config_terms=config_terms,
        after=after,
        after_summary=after_summary,
        frame_range=(int(data.frame.min()), int(data.frame.max())),
    )


def _chosen_physics(
    physics: PhysicsConfig, effects: Sequence[str] | None
) -> tuple[PhysicsConfig, dict[str, type[EffectTerm]]]:
    """The configuration with ``effects`` (if given) as its terms, and the known terms.

    Raises
    ------
    ConfigError
        Empty ``effects`` or a term name the library and plugins do not know.
    """
    if effects is not None:
        effects = [e.strip() for e in effects if e.strip()]
        if not effects:
            raise ConfigError("--effects: give at least one effect term (e.g. trend)")
        physics = physics.model_copy(update={"terms": list(effects)})
    resolve_terms(physics.terms, physics.plugins, key="effects")
    return physics, available_terms(physics.plugins)


def _whiteness(
    run: ModelRun, burn: int
) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, float]]]:
    """Ljung–Box test and periodogram peak of the one-step errors after burn-in, per axis.

    Returns
    -------
    lb : dict
        ``{"x"|"y": {"q", "p_value", "lags"}}``.
    pg : dict
        ``{"x"|"y": {"peak_period_s", "peak_power"}}`` (NaN when too few errors).
    """
    e = run.errors_nm
    lb: dict[str, dict[str, float]] = {}
    pg: dict[str, dict[str, float]] = {}
    for a, axis in enumerate("xy"):
        q, p, lags = ljung_box(e[burn:, a])
        lb[axis] = {"q": q, "p_value": p, "lags": float(lags)}
        periods, power = lomb_scargle(run.t_s[burn:], e[burn:, a])
        if power.size:
            i = int(np.argmax(power))
            pg[axis] = {"peak_period_s": float(periods[i]), "peak_power": float(power[i])}
        else:
            pg[axis] = {"peak_period_s": math.nan, "peak_power": math.nan}
    return lb, pg

"""Model against measurement: compare, locate failures, find the missing effect.

:func:`diagnose` takes the per-frame measurements of a run (:class:`RunData`)
and a physics model (a list of effect terms) and

1. **compares**: re-runs the model online over the measured positions exactly
   as the drift service does (fit on the frames so far, predict the next
   frame, with the channels and events logged up to the end of that frame)
   and summarises the one-step errors; where the session has the true drift,
   also the error of the model's continuous prediction between frames;
2. **locates failures**: episodes of large or persistently biased errors,
   each linked to what was logged then; Ljung–Box, periodogram, CUSUM and
   the up/down frame difference (:mod:`afmdrift.diagnostics._stats`);
3. **finds the missing effect**: tests every library term not in the model
   and the generic response to every logged channel and event kind
   (:mod:`afmdrift.diagnostics._candidates`), ranks them, and for the top
   candidates re-runs the model online with the term added to measure the
   new one-step error ("add it and watch the error fall").

The statistics and the JSON object are documented in ``docs/diagnostics.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._candidates import (
    CandidateResult,
    ModelDesign,
    Thresholds,
    base_basis,
    evaluate_candidate,
    family_candidates,
    ml_phi,
)
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._stats import (
    Failure,
    cross_correlation,
    error_summary,
    find_episodes,
    ljung_box,
    lomb_scargle,
    robust_z,
    up_down_difference,
)
from afmdrift.errors import ConfigError, InputError
from afmdrift.model import (
    CHANNEL_TAU_RANGE_S,
    EffectTerm,
    GenericTerm,
    History,
    HistoryFeed,
    OffsetCurve,
    PhysicsPredictor,
    available_terms,
    resolve_terms,
    term_class,
)
from afmdrift.records import EventKind

__all__ = [
    "DiagnoseOptions",
    "Diagnosis",
    "ModelRun",
    "describe_driver",
    "diagnose",
    "model_design",
    "run_from_store",
    "run_model",
]

FloatArray = npt.NDArray[np.float64]

#: Version of the JSON object (docs/diagnostics.md).
SCHEMA_VERSION = 1


@dataclass(frozen=True, slots=True)
class DiagnoseOptions:
    """Options of :func:`diagnose`.

    Attributes
    ----------
    burn_in_frames : int
        Fed frames at the start whose one-step errors are left out of the
        statistics (every model is poor while it has few points).
    thresholds : Thresholds
        Significance rule of the candidate tests.
    verify : int
        How many testable candidates with the highest ΔAICc are re-run online
        with the term added, besides the significant ones (their
        ``rmse_after_nm`` is then measured, not estimated).
    max_verify : int
        At most this many online re-runs in all (the significant candidates
        with the highest ΔAICc first): with the generic families several
        terms can explain the same residual, and each re-run costs a full
        online fit.
    """

    burn_in_frames: int = 10
    thresholds: Thresholds = field(default_factory=Thresholds)
    verify: int = 2
    max_verify: int = 5


@dataclass(slots=True)
class ModelRun:
    """One online run of a physics model over the measured frames.

    ``t_s`` (m,), ``frames`` (m,), ``measured_nm`` (m, 2), ``predicted_nm``
    (m, 2) and ``errors_nm`` (m, 2) are per fed frame (NaN where no
    prediction was made yet); ``predictor`` is the model after the last
    frame; ``truth_errors_nm`` (q, 2) the continuous prediction error against
    the true drift at ``truth_t_s`` (q,) between frames, when truth exists.
    """

    effects: list[str]
    t_s: FloatArray
    frames: npt.NDArray[np.int64]
    scan_sign: FloatArray
    measured_nm: FloatArray
    predicted_nm: FloatArray
    errors_nm: FloatArray
    predictor: PhysicsPredictor
    history: History
    truth_t_s: FloatArray | None = None
    truth_errors_nm: FloatArray | None = None

    def summary(self, burn_in: int) -> dict[str, float]:
        return error_summary(self.errors_nm[burn_in:])


def run_model(data: RunData, physics: PhysicsConfig, *, truth: bool = True) -> ModelRun:
    """Re-run the physics model online over the fed frames of ``data``.

    Each frame is predicted from the model fitted on the earlier frames, with
    the channels and events logged up to the end of that frame, then added.

    Raises
    ------
    InputError
        If fewer than three frames fed the model.
    ConfigError
        If a term name is unknown.
    """
    obs = data.observations()
    if len(obs) < 3:
        raise InputError(f"only {len(obs)} frames fed the model; need at least 3 to diagnose")
    fed = np.flatnonzero(data.fed)
    predictor = PhysicsPredictor(physics)
    feed = HistoryFeed(data.channels, data.events)
    history = feed.history
    truth_t_all = data.truth_t_s if truth else None
    tt: list[FloatArray] = []
    te: list[FloatArray] = []
    t_end = data.t_end_s[fed]
    for j, o in enumerate(obs):
        upto = float(t_end[j])
        feed.advance(upto)
        predictor.update(o, history)
        if truth_t_all is not None and j + 1 < len(obs) and j >= 1:
            sel = (truth_t_all > upto) & (truth_t_all <= float(t_end[j + 1]))
            if sel.any():
                tq = truth_t_all[sel]
                tt.append(tq)
                te.append(np.asarray(predictor.predict(tq, history).mean_nm, dtype=np.float64))
    errors = np.asarray(predictor.log.errors, dtype=np.float64).reshape(-1, 2)
    measured = predictor.log.xy()
    truth_t = truth_e = None
    if tt:
        truth_t = np.concatenate(tt)
        truth_e = _truth_error(data, truth_t, np.vstack(te), measured, fed)
    return ModelRun(
        effects=list(physics.terms),
        t_s=data.t_s[fed],
        frames=data.frame[fed],
        scan_sign=data.scan_sign[fed],
        measured_nm=measured,
        predicted_nm=measured - errors,
        errors_nm=errors,
        predictor=predictor,
        history=history,
        truth_t_s=truth_t,
        truth_errors_nm=truth_e,
    )


def run_from_store(data: RunData, physics: PhysicsConfig) -> ModelRun | None:
    """The run's own one-step predictions and final model, if it ran ``physics``.

    A run written by ``afmdrift replay`` or the daemon stores the prediction
    it made for every frame and the predictor state after the last one; when
    that predictor is the physics model with exactly this configuration, the
    online re-run of :func:`run_model` would repeat the same computation.
    The continuous error against truth then uses the published curves d(t).
    Returns None when the run cannot be reused.
    """
    state = data.predictor_state
    if data.pred_nm is None or state is None or state.get("name") != PhysicsPredictor.name:
        return None
    try:
        stored = PhysicsConfig.model_validate(state["config"])
    except (KeyError, ValueError):
        return None
    if stored.model_dump() != physics.model_dump():
        return None
    predictor = PhysicsPredictor(physics)
    predictor.load_state_dict(state)
    fed = np.flatnonzero(data.fed)
    measured = data.xy_nm[fed]
    errors = measured - data.pred_nm[fed]
    truth_t = truth_e = None
    if data.truth_t_s is not None and data.curves:
        tt: list[FloatArray] = []
        te: list[FloatArray] = []
        for j in range(1, fed.size - 1):
            doc = data.curves.get(int(data.frame[fed[j]]))
            if doc is None:
                continue
            lo, hi = float(data.t_end_s[fed[j]]), float(data.t_end_s[fed[j + 1]])
            sel = (data.truth_t_s > lo) & (data.truth_t_s <= hi)
            if sel.any():
                tq = data.truth_t_s[sel]
                tt.append(tq)
                te.append(np.asarray(OffsetCurve.from_dict(doc).at(tq), dtype=np.float64))
        if tt:
            truth_t = np.concatenate(tt)
            truth_e = _truth_error(data, truth_t, np.vstack(te), measured, fed)
    return ModelRun(
        effects=list(physics.terms),
        t_s=data.t_s[fed],
        frames=data.frame[fed],
        scan_sign=data.scan_sign[fed],
        measured_nm=measured,
        predicted_nm=data.pred_nm[fed],
        errors_nm=errors,
        predictor=predictor,
        history=data.history(),
        truth_t_s=truth_t,
        truth_errors_nm=truth_e,
    )


def _truth_error(
    data: RunData,
    t_s: FloatArray,
    pred_nm: FloatArray,
    measured_nm: FloatArray,
    fed: npt.NDArray[np.int64],
) -> FloatArray:
    """Continuous prediction minus true drift; p is relative to the reference
    frame and truth to t = 0, so their median difference at the frames is removed."""
    true_c = data.truth_at(t_s)
    true_frames = data.truth_at(data.t_s[fed])
    if true_c is None or true_frames is None:
        raise InputError("the run has no true drift to compare with")
    offset = np.nanmedian(measured_nm - true_frames, axis=0)
    return np.asarray(pred_nm - (true_c + offset[None, :]), dtype=np.float64)


def model_design(run: ModelRun) -> ModelDesign:
    """The final model's basis builder at the frame times, and AR(1) φ per axis.

    φ maximises the conditional likelihood of the model's one-step
    predictions (:func:`~afmdrift.diagnostics._candidates.ml_phi`).
    """
    p = run.predictor
    t = run.t_s
    active = list(p.active)
    known = {term.name: term for term in p.terms}

    def builder(params: dict[str, dict[str, float]]) -> tuple[FloatArray, FloatArray]:
        out = []
        for a in (0, 1):
            blocks = p.design_blocks(t, run.history, run.scan_sign, a, active=active, params=params)
            out.append(np.hstack([b for _, b in blocks]) if blocks else np.zeros((t.size, 0)))
        return out[0], out[1]

    fitted = {k: dict(v) for k, v in p.params.items()}
    phi = ml_phi(run.measured_nm, builder(fitted))
    grids = [
        (name, prm.name, prm.grid()) for name in active for prm in known[name].nonlinear_params
    ]
    return ModelDesign(
        t_s=t,
        y=run.measured_nm,
        scan_sign=run.scan_sign,
        phi=phi,
        builder=builder,
        params=fitted,
        grids=grids,
    )


@dataclass(slots=True)
class Diagnosis:
    """Everything :func:`diagnose` found; :meth:`to_json` is the documented object."""

    model_effects: list[str]
    active_effects: list[str]
    run: ModelRun
    burn_in_frames: int
    summary: dict[str, float]
    truth_summary: dict[str, float] | None
    ljung_box: dict[str, dict[str, float]]
    periodogram: dict[str, dict[str, float]]
    up_down: dict[str, float] | None
    failures: list[Failure]
    patterns: list[str]
    candidates: list[CandidateResult]
    n_tests: int
    thresholds: Thresholds
    phi: list[float]
    finding: str
    config_terms: list[str] | None
    after: ModelRun | None = None
    after_summary: dict[str, float] | None = None

    @property
    def top(self) -> CandidateResult | None:
        """The best significant candidate, or None."""
        for c in self.candidates:
            if c.significant:
                return c
        return None

    def config_snippet(self) -> str | None:
        """The exact lines to put in the configuration file, or None."""
        if self.config_terms is None:
            return None
        terms = ", ".join(f'"{t}"' for t in self.config_terms)
        return f"[model.physics]\nterms = [{terms}]"

    def to_json(self) -> dict[str, Any]:
        """The JSON object documented in docs/diagnostics.md."""
        s = self.summary
        return {
            "schema_version": SCHEMA_VERSION,
            "model_effects": list(self.model_effects),
            "active_effects": list(self.active_effects),
            "frames": int(self.run.t_s.size),
            "burn_in_frames": self.burn_in_frames,
            "rmse_nm": _num(s["rmse_nm"]),
            "rmse_x_nm": _num(s["rmse_x_nm"]),
            "rmse_y_nm": _num(s["rmse_y_nm"]),
            "mean_abs_error_nm": _num(s["mean_abs_nm"]),
            "peak_error_nm": _num(s["peak_nm"]),
            "truth": None
            if self.truth_summary is None
            else {
                "rmse_nm": _num(self.truth_summary["rmse_nm"]),
                "mean_abs_error_nm": _num(self.truth_summary["mean_abs_nm"]),
                "peak_error_nm": _num(self.truth_summary["peak_nm"]),
            },
            "ljung_box": {
                k: {kk: _num(vv) for kk, vv in v.items()} for k, v in self.ljung_box.items()
            },
            "periodogram": {
                k: {kk: _num(vv) for kk, vv in v.items()} for k, v in self.periodogram.items()
            },
            "up_down": None
            if self.up_down is None
            else {k: _num(v) for k, v in self.up_down.items()},
            "ar1_phi": [_num(v) for v in self.phi],
            "patterns": list(self.patterns),
            "failures": [
                {
                    "t_start_s": f.t_start_s,
                    "t_end_s": f.t_end_s,
                    "frames": f.frames,
                    "peak_error_nm": _num(f.peak_error_nm),
                    "kind": f.kind,
                    "context": f.context,
                    "note": f.note,
                }
                for f in self.failures
            ],
            "candidates": [
                {
                    "rank": i + 1,
                    "effect": c.effect,
                    "term": c.effect,
                    "family": _family(c),
                    "testable": c.testable,
                    "reason": c.reason or None,
                    "significant": c.significant,
                    "score": _num(c.score),
                    "delta_aicc": _num(c.delta_aicc),
                    "wald_chi2": _num(c.wald),
                    "df": c.df,
                    "p_value": _num(c.p_value),
                    "p_bonferroni": _num(c.p_bonferroni),
                    "cv_rmse_base_nm": _num(c.cv_rmse_base_nm),
                    "cv_rmse_nm": _num(c.cv_rmse_nm),
                    "cv_drop": None if c.cv_drop is None else _num(c.cv_drop),
                    "prequential_drop": None
                    if c.prequential_drop is None
                    else _num(c.prequential_drop),
                    "params": {**c.driver, **{k: _num(v) for k, v in c.params.items()}},
                    "rmse_after_nm": None if c.rmse_after_nm is None else _num(c.rmse_after_nm),
                    "rmse_after_kind": c.rmse_after_kind,
                    "evidence": c.evidence(),
                }
                for i, c in enumerate(self.candidates)
            ],
            "tests": self.n_tests,
            "thresholds": {
                "min_delta_aicc": self.thresholds.min_delta_aicc,
                "alpha": self.thresholds.alpha,
                "min_cv_drop": self.thresholds.min_cv_drop,
                "folds": self.thresholds.folds,
                "no_cv_factor": self.thresholds.no_cv_factor,
                "generic_min_drop": self.thresholds.generic_min_drop,
                "named_margin_aicc": self.thresholds.named_margin_aicc,
            },
            "finding": self.finding,
            "config": self.config_snippet(),
            "after": None
            if self.after is None or self.after_summary is None
            else {
                "effects": list(self.after.effects),
                "rmse_nm": _num(self.after_summary["rmse_nm"]),
                "mean_abs_error_nm": _num(self.after_summary["mean_abs_nm"]),
                "peak_error_nm": _num(self.after_summary["peak_nm"]),
                "rmse_drop": _num(1.0 - self.after_summary["rmse_nm"] / s["rmse_nm"])
                if s["rmse_nm"] > 0
                else None,
            },
        }


def _patterns(
    data: RunData,
    run: ModelRun,
    burn: int,
    lb: dict[str, dict[str, float]],
    pg: dict[str, dict[str, float]],
    up_down: dict[str, float] | None,
) -> list[str]:
    """Session-wide regularities of the one-step errors, in plain language."""
    out: list[str] = []
    e = run.errors_nm[burn:]
    n = int(np.all(np.isfinite(e), axis=1).sum())
    for axis in ("x", "y"):
        p = lb[axis]["p_value"]
        if math.isfinite(p) and p < 0.01:
            out.append(
                f"{axis} errors are autocorrelated (Ljung-Box p = {p:.2g} over "
                f"{int(lb[axis]['lags'])} lags): something systematic is left in them"
            )
        power, period = pg[axis]["peak_power"], pg[axis]["peak_period_s"]
        if math.isfinite(power) and power > 0.3:
            out.append(
                f"{axis} errors have a periodic component of {period / 3600:.2g} h "
                f"(a sinusoid explains {100 * power:.0f}% of their variance)"
            )
    if n >= 10:
        threshold = max(0.3, 3.0 / math.sqrt(n))
        for name in data.channel_names():
            ct, cv = data.channel_series(name)
            if ct.size < 2:
                continue
            x = np.interp(run.t_s, ct, cv)
            dx = np.concatenate([[np.nan], np.diff(x)])[burn:]
            for a, axis in enumerate("xy"):
                lags, r = cross_correlation(e[:, a], dx, max_lag=3)
                if not np.isfinite(r).any():
                    continue
                i = int(np.nanargmax(np.abs(r)))
                if abs(r[i]) > threshold:
                    out.append(
                        f"{axis} errors follow the changes of {name} (correlation "
                        f"{r[i]:+.2f} at a lag of {int(lags[i])} frame(s))"
                    )
    if up_down is not None and up_down["p_value"] < 0.001:
        out.append(
            f"up and down frames differ: mean error up minus down is "
            f"{up_down['diff_x_nm']:+.2f} nm in x, {up_down['diff_y_nm']:+.2f} nm in y "
            f"(Welch p = {up_down['p_value']:.2g})"
        )
    for k, jump in jumps(run):
        out.append(
            f"the measured drift jumps by ({jump[0]:+.0f}, {jump[1]:+.0f}) nm at "
            f"t = {run.t_s[k]:.0f} s (frame {int(run.frames[k])}), far beyond its other "
            "frame-to-frame changes: a registration mis-lock or a tip change? Check the "
            "worst frame's vector field before trusting a finding"
        )
    return out


#: A frame-to-frame change of p this many robust σ beyond the median is a jump.
JUMP_Z = 20.0
#: After an offset move, a change of p larger than this fraction of the move
#: is a jump (creep and hysteresis stay well below it).
JUMP_MOVE_FRACTION = 0.5
#: ... for moves this many times the median frame-to-frame change of p; the
#: smaller moves of a closed loop following the drift are judged like frames
#: without a move.
JUMP_MOVE_SIZE = 5.0


def jumps(run: ModelRun) -> list[tuple[int, FloatArray]]:
    """Frames whose measured position jumps implausibly, as (index into the
    run, jump (x, y) in nm): a robust z of the Euclidean increment above
    :data:`JUMP_Z`, or, across an offset move of more than
    :data:`JUMP_MOVE_SIZE` median increments, an increment larger than
    :data:`JUMP_MOVE_FRACTION` of the move."""

    inc = np.diff(run.measured_nm, axis=0)
    if inc.shape[0] < 8:
        return []
    size = np.hypot(inc[:, 0], inc[:, 1])
    z = robust_z(size)
    typical = float(np.nanmedian(size))
    mt, steps = run.history.of_kind(EventKind.OFFSET_MOVE)
    moved_by = np.hypot(steps[:, 0], steps[:, 1])
    out: list[tuple[int, FloatArray]] = []
    for i in range(inc.shape[0]):
        t0, t1 = run.t_s[i], run.t_s[i + 1]
        moved = float(moved_by[(mt > t0) & (mt <= t1)].sum())
        if moved > JUMP_MOVE_SIZE * typical:
            if size[i] > JUMP_MOVE_FRACTION * moved:
                out.append((i + 1, inc[i]))
        elif z[i] > JUMP_Z:
            out.append((i + 1, inc[i]))
    return out


def _family(c: CandidateResult) -> str:
    """``named`` for a library or plugin effect, ``channel`` or ``event`` for a generic term."""
    if "channel" in c.driver:
        return "channel"
    if "event_kind" in c.driver:
        return "event"
    return "named"


def _num(v: float | int | None) -> float | None:
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


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
    InputError
        Too few measured frames.
    """
    options = options or DiagnoseOptions()
    physics, known = _chosen_physics(physics, effects)
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
    results, n_tests = _test_candidates(design, run.history, known, physics, options)
    runs = _verify_online(
        results, data, physics, burn=burn, rmse0_nm=summary["rmse_nm"], options=options
    )
    step_s = float(np.median(np.diff(run.t_s))) if run.t_s.size > 1 else math.inf
    _rank(results, options.thresholds, frame_period_s=step_s)
    top = results[0] if results and results[0].significant else None
    after: ModelRun | None = None
    after_summary = None
    if top is not None and top.effect in runs:
        after, after_summary = runs[top.effect]
    finding, config_terms = _finding(
        top, results, physics, summary, after_summary, n_tests, options
    )
    finding = _with_jump_caution(finding, run)
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
        patterns=_patterns(data, run, burn, lb, pg, up_down),
        candidates=results,
        n_tests=n_tests,
        thresholds=options.thresholds,
        phi=[float(v) for v in design.phi],
        finding=finding,
        config_terms=config_terms,
        after=after,
        after_summary=after_summary,
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


def _test_candidates(
    design: ModelDesign,
    history: History,
    known: dict[str, type[EffectTerm]],
    physics: PhysicsConfig,
    options: DiagnoseOptions,
) -> tuple[list[CandidateResult], int]:
    """Added-variable evidence for every candidate term, and the test count.

    Candidates are every known term not in the model and the generic family
    instances of :func:`~afmdrift.diagnostics._candidates.family_candidates`
    (every logged channel, every logged event kind). The count (every θ of
    every testable candidate, over all of them) is the Bonferroni factor, so
    the family-wise false-alarm level holds however many channels, event
    kinds, shapes and time constants are searched.
    """
    terms: dict[str, EffectTerm] = {
        name: cls() for name, cls in known.items() if name not in physics.terms
    }
    for spec in family_candidates(history, physics.terms):
        terms[spec] = term_class(spec, known)()
    testable = [t for t in terms.values() if t.missing(history) is None]
    n_tests = sum(len(t.nonlinear_grid()) for t in testable)
    base = base_basis(design)
    results = []
    for term in terms.values():
        r = evaluate_candidate(
            term, design, history, n_tests=n_tests, thresholds=options.thresholds, base=base
        )
        if isinstance(term, GenericTerm):
            r.driver = term.driver()
        channel = getattr(term, "channel", None)
        r.channel = channel if isinstance(channel, str) else None
        results.append(r)
    return results, n_tests


def _verify_online(
    results: list[CandidateResult],
    data: RunData,
    physics: PhysicsConfig,
    *,
    burn: int,
    rmse0_nm: float,
    options: DiagnoseOptions,
) -> dict[str, tuple[ModelRun, dict[str, float]]]:
    """Re-run the model online with the leading and the significant candidates added.

    Sets each candidate's ``rmse_after_nm`` (replayed, or estimated from the
    blocked CV for those not re-run) and ``prequential_drop``; a candidate
    whose in-sample evidence passes becomes significant when its re-run error
    drops enough, and a candidate whose re-run error rises is not significant.
    At most ``options.max_verify`` re-runs, by ΔAICc; then every named
    candidate whose in-sample evidence passes and whose ΔAICc is within
    :attr:`Thresholds.named_margin_aicc` of a significant generic term is
    re-run too, so that a named effect is never outranked by its generic
    twin (``event:power_on`` and ``warmup``) only because the twin had the
    re-run. Returns the re-runs and their error summaries by effect.
    """
    th = options.thresholds
    by_score = sorted(
        (c for c in results if c.testable),
        key=lambda c: -(c.score if math.isfinite(c.score) else -math.inf),
    )
    runs: dict[str, tuple[ModelRun, dict[str, float]]] = {}

    def rerun(c: CandidateResult) -> None:
        # Prequential check (Dawid 1984): the model with the term, re-run online,
        # predicts every frame before seeing it, like the service.
        cfg = physics.model_copy(update={"terms": [*physics.terms, c.effect]})
        r = run_model(data, cfg)
        s = r.summary(burn)
        runs[c.effect] = (r, s)
        c.rmse_after_nm = s["rmse_nm"]
        c.rmse_after_kind = "replayed"
        if math.isfinite(rmse0_nm) and rmse0_nm > 0 and math.isfinite(s["rmse_nm"]):
            c.prequential_drop = 1.0 - s["rmse_nm"] / rmse0_nm
            if c.in_sample_ok and c.prequential_drop >= th.min_drop(generic=bool(c.driver)):
                c.significant = True
            elif c.prequential_drop < 0:
                # The model re-run online with the term predicts worse than
                # without it: whatever the in-sample and CV evidence, this
                # is not a term to recommend.
                c.significant = False

    for i, c in enumerate(by_score):
        if (i < options.verify or c.significant) and len(runs) < options.max_verify:
            rerun(c)
    generic = [c for c in by_score if c.significant and c.driver]
    for c in by_score:
        if c.driver or c.effect in runs or not c.in_sample_ok:
            continue
        if any(c.delta_aicc >= g.delta_aicc - th.named_margin_aicc for g in generic):
            rerun(c)
    for c in by_score:
        if c.effect in runs:
            continue
        if (
            c.cv_drop is not None
            and math.isfinite(rmse0_nm)
            and 0 < c.cv_rmse_nm <= MAX_CV_RATIO * c.cv_rmse_base_nm
        ):
            c.rmse_after_nm = rmse0_nm * c.cv_rmse_nm / c.cv_rmse_base_nm
            c.rmse_after_kind = "cv_estimate"
    return runs


#: No error estimate from blocked CV when the candidate's cross-validated error is
#: more than this many times the model's: its fit is unstable out of sample
#: (e.g. one amplitude per event with an event near a fold's edge).
MAX_CV_RATIO = 3.0


def _rank(
    results: list[CandidateResult], thresholds: Thresholds, *, frame_period_s: float = 0.0
) -> None:
    """Sort in place: significant first, among them the best online re-run, then by ΔAICc.

    Then, if the first is a generic term (it has a ``driver``) and a
    significant named effect has comparable evidence, the best such named
    effect moves to the front: it names the physics. Comparable: a ΔAICc
    within :attr:`Thresholds.named_margin_aicc` of the generic term's, or an
    online re-run error within :attr:`Thresholds.min_cv_drop` of it (a lag
    filter also smooths a noisy sensor, which can win a generic term a few
    AICc units over a direct named term without predicting any better), or,
    for a generic channel term, the same channel with a fitted lag shorter
    than the frame period ``frame_period_s``: frames cannot resolve such a
    lag, so it is the named direct response with the sensor's noise and
    timing smoothed, not another effect.
    """
    results.sort(
        key=lambda c: (
            not c.significant,
            not c.testable,
            c.rmse_after_nm if (c.significant and c.rmse_after_kind == "replayed") else math.inf,
            -(c.score if math.isfinite(c.score) else -math.inf),
        )
    )
    if not results or not results[0].significant or not results[0].driver:
        return
    lead = results[0]

    def comparable(c: CandidateResult) -> bool:
        if c.delta_aicc >= lead.delta_aicc - thresholds.named_margin_aicc:
            return True
        same_channel = c.channel is not None and c.channel == lead.driver.get("channel")
        if same_channel and lead.nonlinear.get("tau_s", math.inf) < frame_period_s:
            return True
        return (
            c.rmse_after_kind == "replayed"
            and lead.rmse_after_kind == "replayed"
            and c.rmse_after_nm is not None
            and lead.rmse_after_nm is not None
            and c.rmse_after_nm <= (1.0 + thresholds.min_cv_drop) * lead.rmse_after_nm
        )

    for i, c in enumerate(results):
        if c.significant and not c.driver and comparable(c):
            results.insert(0, results.pop(i))
            return


def _with_jump_caution(finding: str, run: ModelRun) -> str:
    """``finding`` prefixed with a caution when the measured drift jumps (see :func:`jumps`)."""
    found_jumps = jumps(run)
    if not found_jumps:
        return finding
    k, jump = found_jumps[0]
    return (
        f"Caution: the measured drift jumps by ({jump[0]:+.0f}, {jump[1]:+.0f}) nm at "
        f"t = {run.t_s[k]:.0f} s ({len(found_jumps)} such jump(s)); if that is a "
        f"measurement error, what follows may explain it rather than physics. {finding}"
    )


def _format_params(c: CandidateResult) -> str:
    """Fitted parameters in words: θ, linear coefficients per axis, refitted model θ."""
    parts = [f"{k} = {v:.3g}" for k, v in c.params.items() if k in c.nonlinear]
    lin: dict[str, list[str]] = {}
    model: list[str] = []
    for k, v in c.params.items():
        if k in c.nonlinear:
            continue
        if k.startswith("model."):
            model.append(f"{k.removeprefix('model.')} = {v:.3g}")
            continue
        base, _, axis = k.rpartition("_")
        lin.setdefault(base, []).append(f"{axis} = {v:.3g}")
    for base, vals in lin.items():
        parts.append(f"{base}: {', '.join(vals)}")
    text = "; ".join(parts)
    if model:
        text += f" (model terms refitted with it: {', '.join(model)})"
    return text


def _finding(
    top: CandidateResult | None,
    results: list[CandidateResult],
    physics: PhysicsConfig,
    summary: dict[str, float],
    after_summary: dict[str, float] | None,
    n_tests: int,
    options: DiagnoseOptions,
) -> tuple[str, list[str] | None]:
    th = options.thresholds
    rule = (
        f"ΔAICc > {th.min_delta_aicc:g}, HAC Wald p < {th.alpha:g} after Bonferroni over "
        f"{n_tests} tests, blocked-CV or online re-run error at least "
        f"{100 * th.min_cv_drop:.0f}% lower ({100 * th.generic_min_drop:.0f}% for a generic "
        "term), online re-run not worse"
    )
    if top is None:
        testable = [c for c in results if c.testable]
        n_generic = sum(1 for c in testable if c.driver)
        best = (
            f" The closest candidate is {testable[0].effect} ({testable[0].evidence()})."
            if testable
            else ""
        )
        return (
            f"No missing effect found: none of the {len(testable) - n_generic} testable "
            f"library effects not in the model and none of the {n_generic} generic terms "
            f"(every logged channel and event kind) passes the test ({rule}).{best}",
            None,
        )
    terms = [*physics.terms, top.effect]
    if top.driver:
        return _generic_finding(top, results, terms, summary, after_summary), terms
    doc = (type(_term_instance(top.effect, physics)).__doc__ or "").strip().splitlines()[0]
    change = _error_change(summary, after_summary)
    return (
        f"Missing effect: {top.effect} ({doc.rstrip('.')}). Fitted: {_format_params(top)}. "
        f"Evidence: {top.evidence()}.{change} To add it, put in your configuration file: "
        f"[model.physics] terms = [{', '.join(repr(t).replace(chr(39), chr(34)) for t in terms)}]",
        terms,
    )


def _duration(t_s: float) -> str:
    """A time constant in words: s below 2 min, min below 2 h, else h."""
    if t_s < 120:
        return f"{t_s:.0f} s"
    if t_s < 7200:
        return f"{t_s / 60:.0f} min"
    return f"{t_s / 3600:.1f} h"


#: How the unit suffixes of channel names read in sentences.
_UNIT_WORDS = {"c": "K", "k": "K", "hpa": "hPa", "pa": "Pa", "pct": "%", "mw": "mW", "v": "V"}


def _gains(c: CandidateResult) -> str:
    """The linear coefficients of ``c`` per axis in words (``+4.1 nm/hPa in x, ...``)."""
    parts = []
    for k, v in c.params.items():
        if k in c.nonlinear or k.startswith("model.") or not math.isfinite(v):
            continue
        base, _, axis = k.rpartition("_")
        if base.startswith("gain_nm_per_"):
            suffix = base.removeprefix("gain_nm_per_")
            unit = f"nm/{_UNIT_WORDS.get(suffix, suffix)}"
        else:
            unit = base.replace("amplitude_nm", "nm").replace("nm_per_decade", "nm per decade")
        parts.append(f"{v:+.3g} {unit} in {axis}")
    return ", ".join(parts)


def describe_driver(c: CandidateResult) -> str:
    """The driver, shape, lag and gain of a generic candidate in plain language."""
    d = c.driver
    if "channel" in d:
        tau = c.nonlinear.get("tau_s", c.params.get("tau_s", math.nan))
        lag = (
            "directly (no lag)"
            if not math.isfinite(tau) or tau <= CHANNEL_TAU_RANGE_S[0]
            else f"through a first-order lag of about {_duration(tau)} (tau_s = {tau:.3g})"
        )
        return f"the residual follows the logged channel {d['channel']} {lag}, {_gains(c)}"
    kind = d.get("event_kind", "?")
    each = "each" in c.effect.split("#")[0].split(":")[2:]
    per = "each event with its own amplitude" if each else "the same amplitude for every event"
    if d.get("shape") == "log":
        t0 = c.nonlinear.get("t0_s", math.nan)
        return (
            f"the residual creeps logarithmically after each logged {kind} event "
            f"(t0 = {t0:.3g} s; {per}), {_gains(c)}"
        )
    tau = c.nonlinear.get("tau_s", math.nan)
    return (
        f"the residual steps after each logged {kind} event and settles exponentially "
        f"with a time constant of about {_duration(tau)} (tau_s = {tau:.3g}; {per}), {_gains(c)}"
    )


def _generic_finding(
    top: CandidateResult,
    results: list[CandidateResult],
    terms: list[str],
    summary: dict[str, float],
    after_summary: dict[str, float] | None,
) -> str:
    """The finding for a generic term: no library effect explains it; driver and shape."""
    named = [c for c in results if c.testable and not c.driver]
    closest = (
        f" (the closest, {named[0].effect}, has ΔAICc = {named[0].delta_aicc:.1f}"
        f"{', significant but far behind' if named[0].significant else ', not significant'})"
        if named
        else ""
    )
    change = _error_change(summary, after_summary)
    quoted = ", ".join(f'"{t}"' for t in terms)
    return (
        f"Missing effect outside the library: {describe_driver(top)}. No library effect "
        f"explains it{closest}. Term: {top.effect}. Evidence: {top.evidence()}.{change} "
        f"To add this term, put in your configuration file: [model.physics] terms = [{quoted}] "
        f"(or --effects {','.join(terms)})."
    )


def _term_instance(name: str, physics: PhysicsConfig) -> EffectTerm:
    return term_class(name, available_terms(physics.plugins))()


def _error_change(summary: dict[str, float], after_summary: dict[str, float] | None) -> str:
    """The finding's sentence on how much adding the candidate cuts the
    one-step error ("" when the model was not re-run with it)."""
    if after_summary is None or not summary["rmse_nm"] > 0:
        return ""
    drop = 1.0 - after_summary["rmse_nm"] / summary["rmse_nm"]
    return (
        f" Re-running the model with it cuts the one-step RMS error from "
        f"{summary['rmse_nm']:.2f} nm to {after_summary['rmse_nm']:.2f} nm "
        f"({100 * drop:.0f}% lower)."
    )

"""The candidates of a diagnosis: their evidence, their online re-runs, their order.

:func:`candidate_evidence` runs the added-variable test
(:func:`~afmdrift.diagnostics._candidates.evaluate_candidate`) on every
library term the model lacks and every generic family instance;
:func:`verify_online` re-runs the model online with the leading candidates
added ("add it and watch the error fall"); :func:`rank_candidates` puts the
one to recommend first.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._candidates import (
    MAX_CV_RATIO,
    CandidateResult,
    ModelDesign,
    Thresholds,
    base_basis,
    evaluate_candidate,
    family_candidates,
)
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._diagnosis import DiagnoseOptions
from afmdrift.diagnostics._discover import (
    STEADY_FRACTION,
    channel_following,
    cycle_steadiness,
    discovered_terms,
    fix_discovered,
    search_tests,
)
from afmdrift.diagnostics._model_run import ModelRun, run_model
from afmdrift.diagnostics._regression import forecast_comparison
from afmdrift.diagnostics._stats import error_summary
from afmdrift.model import DriftShape, EffectTerm, GenericTerm, History, term_class
from afmdrift.runs import TaskPool

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "MAX_CV_RATIO",
    "candidate_evidence",
    "mark_indistinguishable",
    "rank_candidates",
    "verify_online",
]


def candidate_evidence(
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
    kinds, shapes and time constants are searched. With
    ``options.discover`` the drift shapes read from the drift itself
    (:mod:`afmdrift.diagnostics._discover`) are candidates too, and every
    position their search tries counts in the factor.
    """
    terms: dict[str, EffectTerm] = {
        name: cls() for name, cls in known.items() if name not in physics.terms
    }
    for spec in family_candidates(history, physics.terms):
        terms[spec] = term_class(spec, known)()
    if options.discover:
        for shape in discovered_terms(design, physics.terms):
            terms[shape.name] = shape
    testable = [t for t in terms.values() if t.missing(history) is None]
    n_tests = sum(search_tests(t, len(t.nonlinear_grid())) for t in testable)
    base = base_basis(design)
    results = []
    for term in terms.values():
        r = evaluate_candidate(
            term, design, history, n_tests=n_tests, thresholds=options.thresholds, base=base
        )
        if isinstance(term, GenericTerm):
            r.driver = term.driver()
        if isinstance(term, DriftShape) and r.testable:
            fix_discovered(r, term)
            _hold_unsteady_cycle(r, term, design, history, base)
        channel = getattr(term, "channel", None)
        r.channel = channel if isinstance(channel, str) else None
        results.append(r)
    return results, n_tests


def _hold_unsteady_cycle(
    r: CandidateResult, term: DriftShape, design: ModelDesign, history: History, base: object
) -> None:
    """A discovered cycle that is not steady over the record
    (:func:`~afmdrift.diagnostics._discover.cycle_steadiness` below
    :data:`~afmdrift.diagnostics._discover.STEADY_FRACTION`), or that a
    logged channel carries
    (:func:`~afmdrift.diagnostics._discover.channel_following`), fails its
    in-sample evidence; its steadiness and that channel go into
    ``discovered``."""
    if r.discovered is None or r.discovered.get("kind") != "periodic":
        return
    period = r.nonlinear.get("period_s", math.nan)
    steady = cycle_steadiness(term, design, history, base, period)
    r.discovered["steadiness"] = steady if math.isfinite(steady) else None
    follows = channel_following(history, period)
    r.discovered["followed_by"] = follows
    if follows is not None or not (math.isfinite(steady) and steady >= STEADY_FRACTION):
        r.in_sample_ok = False
        r.significant = False


def verify_online(
    results: list[CandidateResult],
    data: RunData,
    physics: PhysicsConfig,
    *,
    base: ModelRun,
    burn: int,
    rmse0_nm: float,
    options: DiagnoseOptions,
    pool: TaskPool,
) -> dict[str, tuple[ModelRun, dict[str, float]]]:
    """Re-run the model online with candidates added, and decide on the re-runs.

    Re-run (prequential check, Dawid 1984: each frame predicted before the
    model sees it, like the service): the ``options.verify`` candidates with
    the highest ΔAICc, every testable candidate with a positive ΔAICc, and
    every named candidate whose in-sample evidence passes and whose ΔAICc is
    within :attr:`Thresholds.named_margin_aicc` of a significant generic term
    (so that a named effect is never outranked by its generic twin only
    because the twin had the re-run); at most ``options.max_verify`` by
    ΔAICc. The re-runs are independent: ``pool`` runs them side by side
    (:class:`~afmdrift.runs.TaskPool`). Each re-run sets ``rmse_after_nm``,
    ``prequential_drop`` and the Diebold-Mariano p-value of its one-step errors against the model's
    (:func:`~afmdrift.diagnostics._regression.forecast_comparison`), adjusted
    over the re-runs by Holm's method.

    **Effect size first:** a candidate is significant only when its re-run
    error is at least :attr:`Thresholds.min_effect` lower, and either its
    in-sample evidence passes (ΔAICc, HAC Wald, blocked CV) or the
    Diebold-Mariano test finds the re-run's improvement significant at
    ``alpha`` (a smooth effect under a random-walk residual, such as a warm-up
    with two time constants, has little power in quasi-differences but shows
    in the predictions); a drift shape read from the drift itself, whose
    position was chosen on the whole record, only by the in-sample route.
    Candidates not re-run are not significant; their ``rmse_after_nm`` is
    estimated from the blocked CV. Returns the re-runs
    and their error summaries by effect.
    """
    th = options.thresholds
    by_score = sorted(
        (c for c in results if c.testable),
        key=lambda c: -(c.score if math.isfinite(c.score) else -math.inf),
    )
    chosen = _to_rerun(by_score, options)
    done = pool.map(rerun_with, [(data, physics, c.effect) for c in chosen])
    runs: dict[str, tuple[ModelRun, dict[str, float]]] = {}
    for c, r in zip(chosen, done, strict=True):
        s = r.summary(burn)
        runs[c.effect] = (r, s)
        e_base, e_new = _compared(c, base, r, burn)
        before = error_summary(e_base)["rmse_nm"] if e_base is not None else rmse0_nm
        after = error_summary(e_new)["rmse_nm"] if e_new is not None else s["rmse_nm"]
        c.rmse_base_nm = before
        c.rmse_after_nm = after
        c.rmse_after_kind = "replayed"
        if math.isfinite(before) and before > 0 and math.isfinite(after):
            c.prequential_drop = 1.0 - after / before
        c.p_online, _ = forecast_comparison(
            base.errors_nm[burn:] if e_base is None else e_base,
            r.errors_nm[burn:] if e_new is None else e_new,
        )
    _holm([c for c in by_score if c.effect in runs])
    for c in by_score:
        if c.effect in runs:
            drop = c.prequential_drop if c.prequential_drop is not None else -math.inf
            # A drift shape's position was chosen on the whole record, so its
            # re-run (the term fixed there from the start) does not pay for
            # that search: only the in-sample route, whose Bonferroni factor
            # counts every position searched, can make it significant.
            online_ok = (
                math.isfinite(c.p_online_holm)
                and c.p_online_holm < th.alpha
                and c.discovered is None
            )
            c.significant = drop >= th.min_effect and (c.in_sample_ok or online_ok)
            continue
        c.significant = False
        if (
            c.cv_drop is not None
            and math.isfinite(rmse0_nm)
            and 0 < c.cv_rmse_nm <= MAX_CV_RATIO * c.cv_rmse_base_nm
        ):
            c.rmse_after_nm = rmse0_nm * c.cv_rmse_nm / c.cv_rmse_base_nm
            c.rmse_after_kind = "cv_estimate"
    return runs


def _compared(
    c: CandidateResult, base: ModelRun, rerun: ModelRun, burn: int
) -> tuple[FloatArray | None, FloatArray | None]:
    """The one-step errors (after burn-in) of the model and of its re-run with
    ``c`` that the online comparison weighs, or (None, None) for all of them.

    A discovered jump leaves out the frames of the jump itself (the frame
    scanned across it and the next): no model predicts a step nobody
    announced, with the term or without it, and the frame where it happens
    would otherwise decide the comparison alone. What the term is judged by
    is how much better the frames after the jump are predicted.
    """
    if c.discovered is None or c.discovered.get("kind") != "jump":
        return None, None
    t = base.t_s[burn:]
    step = float(np.median(np.diff(base.t_s))) if base.t_s.size > 1 else 0.0
    when = c.discovered.get("t_s")
    t_j = float(when) if isinstance(when, int | float) else math.nan
    hide = (t > t_j - 0.5 * step) & (t <= t_j + 1.5 * step)
    e_base = np.where(hide[:, None], np.nan, base.errors_nm[burn:])
    e_new = np.where(hide[:, None], np.nan, rerun.errors_nm[burn:])
    return e_base, e_new


def rerun_with(task: tuple[RunData, PhysicsConfig, str]) -> ModelRun:
    """One online re-run of ``(data, physics, effect)``: the model of
    ``physics`` with the term ``effect`` added, over ``data`` (a task of
    :class:`~afmdrift.runs.TaskPool`, so module-level)."""
    data, physics, effect = task
    cfg = physics.model_copy(update={"terms": [*physics.terms, effect]})
    return run_model(data, cfg)


def _to_rerun(by_score: list[CandidateResult], options: DiagnoseOptions) -> list[CandidateResult]:
    """The candidates :func:`verify_online` re-runs, from their in-sample evidence
    alone (so the re-runs are independent and run side by side). A drift
    shape read from the drift is re-run only when its in-sample evidence
    passes: without it, it cannot be significant (:func:`verify_online`)."""
    th = options.thresholds
    chosen: list[CandidateResult] = []
    eligible = [c for c in by_score if c.discovered is None or c.in_sample_ok]
    for i, c in enumerate(eligible):
        if len(chosen) >= options.max_verify:
            break
        if i < options.verify or c.significant or c.delta_aicc > 0:
            chosen.append(c)
    generic = [c for c in by_score if c.significant and c.driver]
    for c in by_score:
        if c.driver or c.effect in {d.effect for d in chosen} or not c.in_sample_ok:
            continue
        if any(c.delta_aicc >= g.delta_aicc - th.named_margin_aicc for g in generic):
            chosen.append(c)
    return chosen


def _holm(rerun: list[CandidateResult]) -> None:
    """Holm's step-down adjustment (Holm 1979) of the re-runs' Diebold-Mariano
    p-values into ``p_online_holm``: the family-wise error over the re-runs
    stays at the level, with more power than Bonferroni."""
    ordered = sorted(rerun, key=lambda c: c.p_online if math.isfinite(c.p_online) else math.inf)
    m = len(ordered)
    running = 0.0
    for j, c in enumerate(ordered):
        if not math.isfinite(c.p_online):
            c.p_online_holm = math.nan
            continue
        running = max(running, min(1.0, (m - j) * c.p_online))
        c.p_online_holm = running


def mark_indistinguishable(
    results: list[CandidateResult],
    runs: dict[str, tuple[ModelRun, dict[str, float]]],
    base: ModelRun,
    burn: int,
    alpha: float,
) -> None:
    """Set the leading candidate's ``alike``: the other significant candidates
    whose online re-run errors the data cannot tell from its own (neither
    predicts significantly better at ``alpha``, Diebold-Mariano, one-sided
    each way)."""
    if not results or not results[0].significant or results[0].effect not in runs:
        return
    lead = results[0]
    e_lead = runs[lead.effect][0].errors_nm[burn:]
    for c in results[1:]:
        if not c.significant or c.effect not in runs:
            continue
        e_c = runs[c.effect][0].errors_nm[burn:]
        better, _ = forecast_comparison(e_lead, e_c)
        worse, _ = forecast_comparison(e_c, e_lead)
        if not (better < alpha or worse < alpha):
            lead.alike.append(c.effect)


def rank_candidates(
    results: list[CandidateResult], thresholds: Thresholds, *, frame_period_s: float = 0.0
) -> None:
    """Sort in place: significant first, among them the largest drop of the
    online re-run error, then by ΔAICc.

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
    timing smoothed, not another effect. A drift shape read from the drift
    itself (a cycle, a jump, a change of rate) yields the same way to any
    comparable significant candidate that a logged channel or event, or the
    library, explains: "a cycle that no logged channel follows" is said only
    when none does.
    """
    results.sort(
        key=lambda c: (
            not c.significant,
            not c.testable,
            _relative_after(c) if (c.significant and c.rmse_after_kind == "replayed") else math.inf,
            -(c.score if math.isfinite(c.score) else -math.inf),
        )
    )
    if not results or not results[0].significant or not results[0].driver:
        return
    if _discovered(results[0]):
        # A shape read from the drift leads only where nothing logged explains
        # as much: a comparable candidate driven by a logged channel or event
        # (or a library effect) goes first, then the rule below.
        lead = results[0]
        for i, c in enumerate(results):
            if c.significant and not _discovered(c) and _comparable(c, lead, thresholds,
                                                                    frame_period_s):  # fmt: skip
                results.insert(0, results.pop(i))
                break
    lead = results[0]
    if not lead.driver or _discovered(lead):
        _simplest_first(results, thresholds)
        return
    for i, c in enumerate(results):
        if c.significant and not c.driver and _comparable(c, lead, thresholds, frame_period_s):
            results.insert(0, results.pop(i))
            break
    _simplest_first(results, thresholds)


def _discovered(c: CandidateResult) -> bool:
    """Whether ``c`` is a drift shape read from the drift itself."""
    return "drift_shape" in c.driver


def _comparable(
    c: CandidateResult, lead: CandidateResult, thresholds: Thresholds, frame_period_s: float
) -> bool:
    """Whether ``c`` has evidence comparable to ``lead``'s (see :func:`rank_candidates`)."""
    if c.delta_aicc >= lead.delta_aicc - thresholds.named_margin_aicc:
        return True
    same_channel = c.channel is not None and c.channel == lead.driver.get("channel")
    if same_channel and lead.nonlinear.get("tau_s", math.inf) < frame_period_s:
        return True
    if c.rmse_after_kind != "replayed" or lead.rmse_after_kind != "replayed":
        return False
    return _relative_after(c) <= (1.0 + thresholds.min_cv_drop) * _relative_after(lead)


def _relative_after(c: CandidateResult) -> float:
    """A re-run's one-step RMS error over the model's on the same frames (a
    discovered jump's leave out its own frames), or the RMS itself when the
    model's is not recorded; inf when not re-run."""
    if c.rmse_after_nm is None:
        return math.inf
    if c.rmse_base_nm is not None and c.rmse_base_nm > 0:
        return c.rmse_after_nm / c.rmse_base_nm
    return c.rmse_after_nm


def _n_params(c: CandidateResult) -> int:
    """Free parameters of a candidate: its linear coefficients and its θ."""
    return c.df + len(c.nonlinear)


def _simplest_first(results: list[CandidateResult], thresholds: Thresholds) -> None:
    """Parsimony among named effects: when the leading candidate is named and
    a significant named effect with fewer parameters predicts as well (online
    re-run error within :attr:`Thresholds.min_cv_drop`), the simpler one leads
    (``warmup`` before ``warmup_two`` on a warm-up with one time constant)."""
    if not results or not results[0].significant or results[0].driver:
        return
    lead = results[0]
    if lead.rmse_after_nm is None or lead.rmse_after_kind != "replayed":
        return
    simpler = [
        (i, c)
        for i, c in enumerate(results[1:], start=1)
        if c.significant
        and not c.driver
        and c.rmse_after_kind == "replayed"
        and c.rmse_after_nm is not None
        and c.rmse_after_nm <= (1.0 + thresholds.min_cv_drop) * lead.rmse_after_nm
        and _n_params(c) < _n_params(lead)
    ]
    if simpler:
        i, _ = min(simpler, key=lambda ic: (_n_params(ic[1]), ic[1].rmse_after_nm or 0.0))
        results.insert(0, results.pop(i))

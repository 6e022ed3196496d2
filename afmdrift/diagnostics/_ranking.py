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

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._candidates import (
    CandidateResult,
    ModelDesign,
    Thresholds,
    base_basis,
    evaluate_candidate,
    family_candidates,
)
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._diagnosis import DiagnoseOptions
from afmdrift.diagnostics._model_run import ModelRun, run_model
from afmdrift.model import EffectTerm, GenericTerm, History, term_class

__all__ = ["MAX_CV_RATIO", "candidate_evidence", "rank_candidates", "verify_online"]


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


def verify_online(
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


def rank_candidates(
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

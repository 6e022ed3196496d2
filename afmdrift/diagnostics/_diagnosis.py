"""What :func:`~afmdrift.diagnostics.diagnose` found, and its options.

:class:`Diagnosis` holds the comparison, the failures, the ranked candidates
and the finding; :meth:`Diagnosis.to_json` is the object documented in
``docs/diagnostics.md`` (version :data:`SCHEMA_VERSION`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from afmdrift.diagnostics._candidates import CandidateResult, Thresholds
from afmdrift.diagnostics._model_run import ModelRun
from afmdrift.diagnostics._stats import Failure

__all__ = ["SCHEMA_VERSION", "DiagnoseOptions", "Diagnosis"]


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
        with the term added whatever their ΔAICc; beyond them, every testable
        candidate with a positive ΔAICc is (their ``rmse_after_nm`` is then
        measured, not estimated). Only a re-run candidate can be reported as
        missing (effect size first).
    max_verify : int
        At most this many online re-runs in all (the highest ΔAICc first):
        each re-run costs a full online fit, and the Diebold-Mariano p-values
        are corrected for their number.
    discover : bool
        Also test the drift shapes read from the drift itself: a cycle, a
        jump, a change of rate (:mod:`afmdrift.diagnostics._discover`).
    workers : int
        Processes that run the online re-runs side by side on this machine
        (:class:`~afmdrift.runs.TaskPool`; ``afmdrift diagnose`` uses every
        core). Inside a Dask worker the cluster runs them instead. More than
        one spawns processes: a script of your own must then keep its work
        under ``if __name__ == "__main__":``. The result does not depend on it.
    """

    burn_in_frames: int = 10
    thresholds: Thresholds = field(default_factory=Thresholds)
    verify: int = 2
    max_verify: int = 10
    discover: bool = True
    workers: int = 1


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
    plain: str = ""
    after: ModelRun | None = None
    after_summary: dict[str, float] | None = None
    frame_range: tuple[int, int] | None = None

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
            "frame_range": None if self.frame_range is None else list(self.frame_range),
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
                    "in_sample_ok": c.in_sample_ok,
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
                    "p_online": _num(c.p_online),
                    "p_online_holm": _num(c.p_online_holm),
                    "indistinguishable_from": list(c.alike),
                    "discovered": None if c.discovered is None else dict(c.discovered),
                    "params": {**c.driver, **{k: _num(v) for k, v in c.params.items()}},
                    "rmse_after_nm": None if c.rmse_after_nm is None else _num(c.rmse_after_nm),
                    "rmse_after_kind": c.rmse_after_kind,
                    "rmse_base_nm": None if c.rmse_base_nm is None else _num(c.rmse_base_nm),
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
                "min_effect": self.thresholds.min_effect,
                "named_margin_aicc": self.thresholds.named_margin_aicc,
                "look": self.thresholds.look,
                "run_alpha": self.thresholds.run_alpha,
            },
            "plain_finding": self.plain,
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


def _family(c: CandidateResult) -> str:
    """``named`` for a library or plugin effect, ``channel`` or ``event`` for a
    generic term, ``discovered`` for a drift shape read from the drift itself."""
    if "drift_shape" in c.driver:
        return "discovered"
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

"""Model against measurement: where the drift model fails and which effect is missing.

``afmdrift diagnose`` (see ``docs/diagnostics.md`` and
``docs/tutorial-diagnose.md``) compares the physics model's one-step
predictions with the measured drift, locates failure episodes, and tests every
effect of the library (:mod:`afmdrift.model._effects`) that the model lacks.

Public API
----------
:class:`RunData`, :func:`load_run`
    Per-frame measurements of a run, with channels and events.
:func:`diagnose`, :class:`Diagnosis`, :class:`DiagnoseOptions`
    The whole analysis; :meth:`Diagnosis.to_json` is the documented object.
:func:`run_model`, :class:`ModelRun`
    Online re-run of a physics model over the measured frames.
:func:`evaluate_candidate`, :class:`CandidateResult`, :class:`Thresholds`
    Added-variable test of one effect term.
:func:`write_report`
    Self-contained HTML report.
:func:`diagnose_path`, :func:`diagnosis_text`
    ``afmdrift diagnose``: a run or session directory to a diagnosis, and
    the text it prints.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from afmdrift.diagnostics._candidates import (
    CandidateResult,
    ModelDesign,
    Thresholds,
    evaluate_candidate,
)
from afmdrift.diagnostics._data import RunData, load_run
from afmdrift.diagnostics._diagnose import DiagnoseOptions, Diagnosis, diagnose
from afmdrift.diagnostics._model_run import ModelRun, run_model
from afmdrift.diagnostics._run import diagnose_path, is_run_dir
from afmdrift.diagnostics._stats import Failure
from afmdrift.diagnostics._text import diagnosis_text

if TYPE_CHECKING:
    from afmdrift.diagnostics._report import write_report

__all__ = [
    "CandidateResult",
    "DiagnoseOptions",
    "Diagnosis",
    "Failure",
    "ModelDesign",
    "ModelRun",
    "RunData",
    "Thresholds",
    "diagnose",
    "diagnose_path",
    "diagnosis_text",
    "evaluate_candidate",
    "is_run_dir",
    "load_run",
    "run_model",
    "write_report",
]


def __getattr__(name: str) -> Any:
    if name == "write_report":  # matplotlib is imported only when a report is written
        from afmdrift.diagnostics._report import write_report

        return write_report
    raise AttributeError(f"module 'afmdrift.diagnostics' has no attribute {name!r}")

"""From a session or run directory to a :class:`Diagnosis`.

A session directory (format v1) is first run through the drift service's
pipeline with :func:`afmdrift.runs.replay_session`, the function behind
``afmdrift replay``, so the diagnosis sees exactly what the daemon would have
measured and predicted. A run directory (``run.sqlite``) is read as it is.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

from afmdrift.config import AfmdriftConfig
from afmdrift.diagnostics._data import RunData, load_run
from afmdrift.diagnostics._diagnose import DiagnoseOptions, Diagnosis, diagnose
from afmdrift.diagnostics._driftlog import load_drift_log
from afmdrift.errors import InputError
from afmdrift.runs import DB_NAME, effective_model, replay_session
from afmdrift.session import is_drift_log

__all__ = ["config_with_effects", "diagnose_path", "is_run_dir", "prepare_run"]


def is_run_dir(path: str | Path) -> bool:
    """True if ``path`` holds a run store (else it should be a session)."""

    return (Path(path) / DB_NAME).is_file()


def config_with_effects(config: AfmdriftConfig, effects: Sequence[str] | None) -> AfmdriftConfig:
    """``config`` with ``[model.physics] terms`` replaced by ``effects`` (if given)."""
    if effects is None:
        return config
    physics = config.model.physics.model_copy(update={"terms": list(effects)})
    model = config.model.model_copy(update={"physics": physics})
    return config.model_copy(update={"model": model})


def prepare_run(
    path: str | Path,
    *,
    config: AfmdriftConfig,
    effects: Sequence[str] | None = None,
    run_dir: str | Path | None = None,
    session_dir: str | Path | None = None,
    prior_px: tuple[float, float] | None = None,
) -> RunData:
    """Measurements of ``path``: read a run directory, or replay a session first
    (``prior_px``: the expected drift of its first frame after the first, px).

    Parameters
    ----------
    path : path-like
        A run directory or a session directory.
    config : AfmdriftConfig
        Configuration for the replay (registration, model, service).
    effects : sequence of str, optional
        Model terms for the replay (default: ``config.model.physics.terms``).
    run_dir : path-like, optional
        Where a replay writes its run (default: a temporary directory that is
        removed afterwards); must be empty or absent.
    session_dir : path-like, optional
        For a run directory: its session, for truth and frame images.

    Raises
    ------
    InputError
        ``path`` is neither a run nor a session, or the replay fails.
    """
    p = Path(path)
    if not p.is_dir():
        raise InputError(f"{p}: not a directory (expected a session or a run directory)")
    if is_run_dir(p):
        return load_run(p, session_dir=session_dir)
    if is_drift_log(p):
        return load_drift_log(p)
    if not (p / "session.json").is_file():
        raise InputError(
            f"{p}: neither a run directory (run.sqlite), a session (session.json) "
            "nor a drift log (positions.csv)"
        )

    cfg = config_with_effects(config, effects)
    if run_dir is not None:
        replay_session(p, run_dir, config=cfg, prior_px=prior_px)
        return load_run(run_dir, session_dir=p)
    with tempfile.TemporaryDirectory(prefix="afmdrift-diagnose-") as tmp:
        replay_session(p, tmp, config=cfg, prior_px=prior_px)
        return load_run(tmp, session_dir=p)


def diagnose_path(
    path: str | Path,
    *,
    config: AfmdriftConfig,
    effects: Sequence[str] | None = None,
    run_dir: str | Path | None = None,
    session_dir: str | Path | None = None,
    options: DiagnoseOptions | None = None,
    prior_px: tuple[float, float] | None = None,
) -> tuple[Diagnosis, RunData]:
    """:func:`prepare_run` then :func:`diagnose` with the configured physics model.

    A run whose model changed while it ran (``afmdrift control add-term``) is
    diagnosed with the terms it ended with, the configured ones with the
    run's changes applied (:func:`~afmdrift.runs.effective_model`), unless
    ``effects`` names them: the diagnosis says what that model still misses.
    """
    data = prepare_run(
        path,
        config=config,
        effects=effects,
        run_dir=run_dir,
        session_dir=session_dir,
        prior_px=prior_px,
    )
    model = config.model
    if data.model_changes:
        model = effective_model(model, data.model_changes)
    return diagnose(data, model.physics, effects=effects, options=options), data

"""One online run of a physics model over the measured frames of a run.

:func:`run_model` re-runs the model exactly as the drift service does: each
fed frame is predicted from the model fitted on the frames before it, with
the channels and events logged up to the end of that frame, then added.
:func:`run_from_store` takes the run's own predictions instead when the run
already ran this very model. :func:`model_design` turns a run's final model
into the design the candidate tests extend
(:mod:`afmdrift.diagnostics._candidates`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._candidates import ModelDesign
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._regression import ml_phi
from afmdrift.diagnostics._stats import error_summary
from afmdrift.errors import InputError
from afmdrift.model import History, HistoryFeed, OffsetCurve, PhysicsPredictor

__all__ = ["ModelRun", "model_design", "run_from_store", "run_model"]

FloatArray = npt.NDArray[np.float64]


@dataclass(slots=True)
class ModelRun:
    """One online run of a physics model over the measured frames.

    ``samples`` (m, k) are the times each position averages over (its scan
    window, :meth:`RunData.samples`); ``t_s`` (m,), ``frames`` (m,),
    ``measured_nm`` (m, 2), ``predicted_nm`` (m, 2) and ``errors_nm`` (m, 2)
    are per fed frame (NaN where no prediction was made yet); ``predictor``
    is the model after the last frame; ``truth_errors_nm`` (q, 2) the
    continuous prediction error against the true drift at ``truth_t_s`` (q,)
    between frames, when truth exists.
    """

    effects: list[str]
    t_s: FloatArray
    samples: FloatArray
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
        samples=data.samples(fed),
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
    Returns None when the run cannot be reused, as for a run whose model
    changed while it ran (its predictions come from more than one model).
    """
    state = data.predictor_state
    if data.pred_nm is None or state is None or state.get("name") != PhysicsPredictor.name:
        return None
    if data.model_changes:
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
        samples=data.samples(fed),
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
    predictions (:func:`~afmdrift.diagnostics._regression.ml_phi`).
    """
    p = run.predictor
    t = run.samples
    active = list(p.active)
    known = {term.name: term for term in p.terms}

    def builder(params: dict[str, dict[str, float]]) -> tuple[FloatArray, FloatArray]:
        out = []
        for a in (0, 1):
            blocks = p.design_blocks(t, run.history, run.scan_sign, a, active=active, params=params)
            out.append(np.hstack([b for _, b in blocks]) if blocks else np.zeros((t.shape[0], 0)))
        return out[0], out[1]

    fitted = {k: dict(v) for k, v in p.params.items()}
    phi = ml_phi(run.measured_nm, builder(fitted))
    grids = [
        (name, prm.name, prm.grid()) for name in active for prm in known[name].nonlinear_params
    ]
    return ModelDesign(
        t_s=run.t_s,
        samples=t,
        y=run.measured_nm,
        scan_sign=run.scan_sign,
        phi=phi,
        builder=builder,
        params=fitted,
        grids=grids,
    )

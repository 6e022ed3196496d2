"""Offline evaluation of drift predictors over a replayed run.

``afmdrift evaluate`` is "replay, then score": the session first goes through
the daemon's own pipeline (:func:`afmdrift.runs.measure_session`, the
code ``afmdrift replay`` and the daemon run), which gives each frame's
observation exactly as the daemon fed it to its model (the latest sample of
the causal drift trajectory) in a :class:`MeasuredSeries`. Then
:func:`evaluate_series` replays those observations, in time order, through
several predictors side by side. For every predictor it scores

* the **one-step prediction error**: before frame i is shown to the
  predictor, its prediction at the frame's observation time t_i minus the
  observed p_i; and, where the session has ``truth.csv``, its predicted
  sample position (``predict_drift``, without measurement artefacts) minus
  the true p(t_i) (relative to the true p at the session reference's
  mid-scan time, where p = 0 by definition);
* the **continuous-offset error** (truth only): after frame i is complete
  (t_end_i) the predictor is updated and a curve d(t) is built; it is what
  the tip follows until the next frame completes, so it is compared with the
  true p(t) on a dense grid over [t_end_i, t_end_{i+1}), for both
  reconstructions;
* **timing**: wall time of update, prediction and curve building per frame.

So every score is one the daemon can reach online: nothing uses later frames.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import ModelConfig
from afmdrift.errors import TooFewFramesError
from afmdrift.model._base import Observation
from afmdrift.model._feed import HistoryFeed
from afmdrift.model._reconstruct import OffsetCurve, build_offset_curve
from afmdrift.model._registry import make_predictor
from afmdrift.records import ScanDirection
from afmdrift.session import DriftLog, Session

__all__ = ["FIRST_SCORED_FRAME", "MeasuredSeries", "evaluate_series"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: Spacing of the dense truth comparison of d(t), s.
DENSE_STEP_S = 2.0

#: The first valid frame (counted from 0) whose one-step error can be scored,
#: the least ``skip``: a predictor predicts only from an observation, and
#: valid frame 0 is its first. Scoring from valid frame ``skip`` on needs
#: ``skip + 1`` valid frames.
FIRST_SCORED_FRAME = 1


@dataclass(slots=True)
class MeasuredSeries:
    """The observations a session's frames gave the daemon's model.

    One entry per frame: ``t_s`` the observation time (the frame's latest
    drift trajectory sample; the mid-scan time where it fed nothing),
    ``xy_nm`` (n, 2) the observed p (NaN where the frame did not feed the
    model), ``sigma_nm`` its uncertainty, ``t_end_s`` frame completion times,
    ``measure_ms`` the pipeline's time per frame, ``reference_direction`` the
    scan direction of the session reference the positions are measured
    against (None: unknown), ``window_s`` (n, 2) the scan window each position
    averages over where it is a whole frame's (None or NaN rows: points).
    """

    t_s: FloatArray
    t_end_s: FloatArray
    xy_nm: FloatArray
    sigma_nm: FloatArray
    directions: list[ScanDirection]
    measure_ms: FloatArray
    valid_blocks: list[int] = field(default_factory=list)
    reference_direction: ScanDirection | None = None
    window_s: FloatArray | None = None

    def observation(self, i: int) -> Observation:
        """Entry ``i`` as the model observation it feeds."""
        sigma = float(self.sigma_nm[i])
        window = Observation.window_of(None if self.window_s is None else self.window_s[i])
        return Observation(
            t_s=float(self.t_s[i]),
            x_nm=float(self.xy_nm[i, 0]),
            y_nm=float(self.xy_nm[i, 1]),
            sigma_nm=sigma if math.isfinite(sigma) else 0.0,
            direction=self.directions[i],
            frame=i,
            reference_direction=self.reference_direction,
            window_s=window,
        )


def _stats(e: FloatArray) -> dict[str, Any]:
    """mean |e|, RMS and peak per axis, of the Euclidean norm, and pooled over axes."""
    e = e[np.all(np.isfinite(e), axis=1)]
    if e.shape[0] == 0:
        return {"n": 0}
    norm = np.hypot(e[:, 0], e[:, 1])
    out: dict[str, Any] = {"n": int(e.shape[0])}
    for name, v in (("x", e[:, 0]), ("y", e[:, 1]), ("norm", norm), ("pooled", e.ravel())):
        out[name] = {
            "mean_abs_nm": float(np.mean(np.abs(v))),
            "rms_nm": float(np.sqrt(np.mean(v**2))),
            "peak_nm": float(np.max(np.abs(v))),
        }
    return out


def evaluate_series(
    session: Session | DriftLog,
    series: MeasuredSeries,
    *,
    predictors: list[str],
    config: ModelConfig,
    skip: int = 2,
    reconstructions: tuple[str, ...] = ("hermite", "sinc"),
) -> dict[str, Any]:
    """Replay ``series`` through each predictor; return the report (see docs/model.md).

    Parameters
    ----------
    session : Session or DriftLog
        Source of channels, events, frame timing and (optional) truth.
    series : MeasuredSeries
        From :func:`measure_session`.
    predictors : list of str
        Predictor names (:data:`afmdrift.model.PREDICTOR_NAMES`).
    config : ModelConfig
    skip : int
        One-step errors are scored from the ``skip``-th valid frame on (every
        predictor on the same frames); at least :data:`FIRST_SCORED_FRAME`.
    reconstructions : tuple of str
        Curve kinds compared with truth.

    Raises
    ------
    ValueError
        ``skip`` is below :data:`FIRST_SCORED_FRAME`.
    TooFewFramesError
        Fewer than ``skip + 1`` valid frames: no one-step error to score.
    """
    if skip < FIRST_SCORED_FRAME:
        raise ValueError(f"skip must be >= {FIRST_SCORED_FRAME}, got {skip}")
    valid = np.all(np.isfinite(series.xy_nm), axis=1)
    idx = np.nonzero(valid)[0]
    if idx.size < skip + 1:
        raise TooFewFramesError(
            int(idx.size),
            skip + 1,
            why=f"one-step errors are scored from valid frame {skip} on",
        )
    period = float(np.median(np.diff(series.t_s))) if series.t_s.size > 1 else 1.0
    truth_t = truth_xy = None
    ref = np.zeros(2)
    frame_truth = np.full((len(session), 2), np.nan)
    if session.truth is not None:
        truth_t = session.truth[:, 0]
        truth_xy = session.truth[:, 1:3]
        t0 = float(np.mean(session.frame_times[0]))
        ref = np.array([np.interp(t0, truth_t, truth_xy[:, a]) for a in (0, 1)])
        for i in range(len(session)):
            frame_truth[i] = [
                np.interp(series.t_s[i], truth_t, truth_xy[:, a]) - ref[a] for a in (0, 1)
            ]
    report: dict[str, Any] = {
        "frames": len(session),
        "valid_frames": int(valid.sum()),
        "frame_period_s": period,
        "skip": skip,
        "truth": session.truth is not None,
        "measurement": {
            "time_per_frame_ms": {
                "mean": float(np.mean(series.measure_ms)),
                "max": float(np.max(series.measure_ms)),
            },
        },
        "predictors": {},
    }
    if session.truth is not None:
        meas_err = series.xy_nm[valid] - frame_truth[valid]
        report["measurement"]["vs_truth"] = _stats(meas_err[1:])
    for name in predictors:
        report["predictors"][name] = _run_one(
            name, session, series, idx, config, skip, reconstructions,
            truth_t, truth_xy, ref, frame_truth, period,
        )  # fmt: skip
    return report


def _run_one(
    name: str,
    session: Session | DriftLog,
    series: MeasuredSeries,
    idx: npt.NDArray[np.intp],
    config: ModelConfig,
    skip: int,
    reconstructions: tuple[str, ...],
    truth_t: FloatArray | None,
    truth_xy: FloatArray | None,
    ref: FloatArray,
    frame_truth: FloatArray,
    period: float,
) -> dict[str, Any]:
    predictor = make_predictor(name, config)
    feed = HistoryFeed(session.channel_samples(), session.events)
    err_meas = np.full((idx.size, 2), np.nan)
    err_truth = np.full((idx.size, 2), np.nan)
    t_update = np.zeros(idx.size)
    t_predict = np.zeros(idx.size)
    t_curve = np.zeros(idx.size)
    curves: dict[str, list[tuple[float, OffsetCurve]]] = {k: [] for k in reconstructions}
    previous: dict[str, OffsetCurve | None] = dict.fromkeys(reconstructions)
    for k, i in enumerate(idx):
        t_i = float(series.t_s[i])
        t_done = float(series.t_end_s[i])
        feed.advance(t_done)
        history = feed.history
        obs = series.observation(int(i))
        if k >= skip:
            t0 = time.perf_counter()
            pred, _ = predictor.predict_observation(obs, history)
            t_predict[k] = (time.perf_counter() - t0) * 1e3
            err_meas[k] = pred - series.xy_nm[i]
            if truth_t is not None:
                drift = predictor.predict_drift([t_i], history).mean_nm[0]
                err_truth[k] = drift - frame_truth[i]
        t0 = time.perf_counter()
        predictor.update(obs, history)
        t_update[k] = (time.perf_counter() - t0) * 1e3
        if truth_t is None:
            continue
        t_obs, xy_obs = predictor.observed()
        for kind in reconstructions:
            t0 = time.perf_counter()
            curve = build_offset_curve(
                "sinc" if kind == "sinc" else "hermite",
                predictor,
                history,
                t_now_s=t_done,
                measured_t_s=t_obs,
                measured_nm=xy_obs,
                frame_period_s=period,
                lookahead=config.lookahead,
                previous=previous[kind],
                blend_s=config.blend_fraction * period,
            )
            if kind == config.reconstruction:
                t_curve[k] = (time.perf_counter() - t0) * 1e3
            previous[kind] = curve
            curves[kind].append((t_done, curve))
    out: dict[str, Any] = {
        "one_step": {"vs_measured": _stats(err_meas[skip:])},
        "timing_ms": {
            "update_mean": float(np.mean(t_update)),
            "update_max": float(np.max(t_update)) if t_update.size else 0.0,
            "predict_mean": float(np.mean(t_predict[skip:])) if idx.size > skip else 0.0,
            "curve_mean": float(np.mean(t_curve)),
            "per_frame_mean": float(np.mean(t_update + t_predict + t_curve)),
        },
    }
    if truth_t is not None and truth_xy is not None:
        out["one_step"]["vs_truth"] = _stats(err_truth[skip:])
        out["continuous"] = {}
        for kind in reconstructions:
            errs = []
            segs = curves[kind]
            for (t_a, curve), (t_b, _) in zip(segs[skip:-1], segs[skip + 1 :], strict=True):
                tt = np.arange(t_a, t_b, DENSE_STEP_S)
                true = np.column_stack(
                    [np.interp(tt, truth_t, truth_xy[:, 0]), np.interp(tt, truth_t, truth_xy[:, 1])]
                )
                errs.append(curve.at(tt) - (true - ref))
            e = np.vstack(errs) if errs else np.zeros((0, 2))
            out["continuous"][kind] = _stats(e)
    return out

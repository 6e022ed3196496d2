"""Offline evaluation of drift predictors on a recorded session.

:func:`measure_session` runs the registration engine over a session exactly as
the service does (a :class:`~afmdrift.registration.DriftTracker` over the
frames), turns image positions into drift positions with
:func:`~afmdrift.model.drift_from_measurements`, and :func:`evaluate_series`
replays them, frame by frame and in time order, through several predictors
side by side. For every predictor it scores

* the **one-step prediction error**: before frame i is shown to the
  predictor, its prediction at t_i (mid-scan) minus the measured p_i; and,
  where the session has ``truth.csv``, its predicted sample position
  (``predict_drift``, without measurement artefacts) minus the true p
  averaged over the frame's row times;
* the **continuous-offset error** (truth only): after frame i is complete
  (t_end_i) the predictor is updated and a curve d(t) is built; it is what
  the tip follows until the next frame completes, so it is compared with the
  true p(t) on a dense grid over [t_end_i, t_end_{i+1}), for both
  reconstructions;
* **timing**: wall time of update, prediction and curve building per frame.

Reference: measured positions are relative to frame 0 (p = 0 there, by
definition of the registration reference), whose measurement sees the mean of
the true drift over its row times; truth is shifted by that mean so both share
the reference.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import ModelConfig, RegistrationConfig
from afmdrift.model._base import Observation
from afmdrift.model._feed import HistoryFeed
from afmdrift.model._positions import (
    correct_slow_axis_timing,
    drift_from_measurements,
    frames_spanning_moves,
    truth_frame_mean,
)
from afmdrift.model._reconstruct import OffsetCurve, build_offset_curve
from afmdrift.model._registry import make_predictor
from afmdrift.records import ScanDirection
from afmdrift.registration import DriftTracker
from afmdrift.session import Session

__all__ = ["MeasuredSeries", "evaluate_series", "measure_session"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: Spacing of the dense truth comparison of d(t), s.
DENSE_STEP_S = 2.0


@dataclass(slots=True)
class MeasuredSeries:
    """Drift positions of a session's frames, as the service would see them.

    ``xy_nm`` (n, 2) is NaN where the measurement was invalid; ``t_s`` are
    mid-scan times, ``t_end_s`` frame completion times.
    """

    t_s: FloatArray
    t_end_s: FloatArray
    xy_nm: FloatArray
    sigma_nm: FloatArray
    directions: list[ScanDirection]
    measure_ms: FloatArray
    valid_blocks: list[int] = field(default_factory=list)


def measure_session(
    session: Session, config: RegistrationConfig, *, timing_correction: bool = True
) -> MeasuredSeries:
    """Run the registration engine over every frame and convert to drift positions.

    Commanded offset moves are added back (:func:`drift_from_measurements`),
    frames scanned across a move are dropped (:func:`frames_spanning_moves`)
    and, unless ``timing_correction`` is False, the raster-timing bias of each
    measurement against its reference frame is removed
    (:func:`correct_slow_axis_timing`).
    """
    tracker = DriftTracker(pixel_size_nm=session.meta.pixel_size_nm, config=config)
    n = len(session)
    m = np.full((n, 2), np.nan)
    sigma = np.full(n, np.nan)
    ms = np.zeros(n)
    blocks: list[int] = []
    reference = [-1] * n
    for i, frame in enumerate(session.iter_frames()):
        t0 = time.perf_counter()
        step = tracker.update(np.asarray(frame.heights_nm))
        ms[i] = (time.perf_counter() - t0) * 1e3
        if step is None:
            m[i] = 0.0
            sigma[i] = 0.0
            blocks.append(-1)
            continue
        meas = step.measurement
        blocks.append(int(meas.valid_blocks))
        if step.accepted:
            m[i] = np.asarray(step.position_nm, dtype=np.float64).reshape(2)
            sigma[i] = float(meas.sigma_nm)
            reference[i] = int(step.reference_index)
        else:
            _log.info("frame %d: measurement not accepted (%s)", i, meas.reason)
    frames = list(session.iter_frames())
    t = np.array([f.t_mid_s for f in frames])
    spanning = frames_spanning_moves(session.frame_times, session.events)
    for k in np.nonzero(spanning)[0]:
        _log.info("frame %d: an offset move happened during its scan; not used", int(k))
    m[spanning] = np.nan
    p = drift_from_measurements(t, m, session.events, t_ref_s=float(t[0]))
    if timing_correction:
        slope = np.array(
            [f.line_time_s if f.direction is ScanDirection.UP else -f.line_time_s for f in frames]
        )
        p = correct_slow_axis_timing(
            t, p, m, reference, slope, pixel_size_y_nm=session.meta.pixel_size_nm[1]
        )
    return MeasuredSeries(
        t_s=t,
        t_end_s=session.frame_times[:, 1].copy(),
        xy_nm=p,
        sigma_nm=sigma,
        directions=list(session.directions),
        measure_ms=ms,
        valid_blocks=blocks,
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
    session: Session,
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
    session : Session
        Source of channels, events, frame timing and (optional) truth.
    series : MeasuredSeries
        From :func:`measure_session`.
    predictors : list of str
        Predictor names (:data:`afmdrift.model.PREDICTOR_NAMES`).
    config : ModelConfig
    skip : int
        One-step errors are scored from the ``skip``-th valid frame on (every
        predictor on the same frames).
    reconstructions : tuple of str
        Curve kinds compared with truth.
    """
    valid = np.all(np.isfinite(series.xy_nm), axis=1)
    idx = np.nonzero(valid)[0]
    period = float(np.median(np.diff(series.t_s))) if series.t_s.size > 1 else 1.0
    truth_t = truth_xy = None
    ref = np.zeros(2)
    frame_truth = np.full((len(session), 2), np.nan)
    if session.truth is not None:
        truth_t = session.truth[:, 0]
        truth_xy = session.truth[:, 1:3]
        ref = truth_frame_mean(session.frame(0), truth_t, truth_xy)
        for i in range(len(session)):
            frame_truth[i] = truth_frame_mean(session.frame(i), truth_t, truth_xy) - ref
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
    session: Session,
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
        if k >= skip:
            t0 = time.perf_counter()
            pred = predictor.predict([t_i], history).mean_nm[0]
            t_predict[k] = (time.perf_counter() - t0) * 1e3
            err_meas[k] = pred - series.xy_nm[i]
            if truth_t is not None:
                drift = predictor.predict_drift([t_i], history).mean_nm[0]
                err_truth[k] = drift - frame_truth[i]
        obs = Observation(
            t_s=t_i,
            x_nm=float(series.xy_nm[i, 0]),
            y_nm=float(series.xy_nm[i, 1]),
            sigma_nm=float(series.sigma_nm[i]) if math.isfinite(series.sigma_nm[i]) else 0.0,
            direction=series.directions[i],
            frame=int(i),
        )
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

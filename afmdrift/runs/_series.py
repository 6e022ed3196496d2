"""A whole session through the pipeline: what the daemon would have fed its
model, for ``afmdrift evaluate`` (:func:`~afmdrift.model.evaluate_series`);
and the positions of a drift log as the same series."""

from __future__ import annotations

import math

import numpy as np

from afmdrift.config import AfmdriftConfig
from afmdrift.model import MeasuredSeries
from afmdrift.pipeline import (
    FrameRecord,
    observation_from_record,
    reference_direction_of,
)
from afmdrift.records import ScanDirection
from afmdrift.runs._session import session_pipeline
from afmdrift.session import DriftLog, Session

__all__ = ["measure_session", "series_from_drift_log", "series_from_records"]


def series_from_records(records: list[FrameRecord]) -> MeasuredSeries:
    """The observations the frames gave the model (see :class:`MeasuredSeries`),
    from the records of a run: the daemon's store, or :func:`measure_session`."""
    n = len(records)
    t = np.empty(n)
    xy = np.full((n, 2), np.nan)
    sigma = np.full(n, np.nan)
    reference = reference_direction_of(records)
    for i, r in enumerate(records):
        if r.fed_model:
            obs = observation_from_record(r, reference)
            t[i], xy[i], sigma[i] = obs.t_s, (obs.x_nm, obs.y_nm), obs.sigma_nm
        else:
            t[i] = r.t_mid_s
    return MeasuredSeries(
        t_s=t,
        t_end_s=np.array([r.t_end_s for r in records], dtype=np.float64),
        xy_nm=xy,
        sigma_nm=sigma,
        directions=[ScanDirection(r.direction) for r in records],
        measure_ms=np.array([r.latency_s * 1e3 for r in records], dtype=np.float64),
        valid_blocks=[int(r.valid_blocks) if math.isfinite(r.x_nm) else -1 for r in records],
        reference_direction=reference,
    )


def series_from_drift_log(log: DriftLog) -> MeasuredSeries:
    """The observations of a drift log (its positions as measured elsewhere; a
    frame without one fed nothing; a frame's position averages over its scan
    window), for ``afmdrift evaluate DIR``."""
    known = [d for d, ok in zip(log.directions, np.isfinite(log.xy_nm[:, 0]), strict=True) if ok]
    return MeasuredSeries(
        t_s=log.t_s.copy(),
        t_end_s=log.frame_times[:, 1].copy(),
        xy_nm=log.xy_nm.copy(),
        sigma_nm=log.sigma_nm.copy(),
        directions=list(log.directions),
        measure_ms=np.zeros(len(log)),
        valid_blocks=[-1] * len(log),
        reference_direction=known[0] if known else None,
        window_s=log.frame_times.copy(),
    )


def measure_session(
    session: Session, config: AfmdriftConfig, *, prior_px: tuple[float, float] | None = None
) -> MeasuredSeries:
    """Run every frame of ``session`` through :class:`FramePipeline`, as
    ``afmdrift replay`` and the daemon do (the session's channels and events
    known from the start, each reaching the model with the first frame that
    ends after it), and return what the frames gave the model."""
    pipeline = session_pipeline(session, config, prior_px=prior_px)
    records = [outcome.record for outcome in pipeline.run(session.iter_frames())]
    return series_from_records(records)

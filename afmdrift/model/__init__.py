"""Drift prediction and reconstruction of the continuous offset d(t).

Importing this package does not import torch; :class:`NNPredictor` and
:class:`NNSeriesModel` load it on first access.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from afmdrift.config import KalmanConfig, ModelConfig, NNConfig, PhysicsConfig
from afmdrift.model._base import (
    History,
    Observation,
    OffsetPlay,
    Prediction,
    Predictor,
    events_of_kind,
    scan_samples,
)
from afmdrift.model._baselines import ConstantVelocityPredictor, LastValuePredictor
from afmdrift.model._effects import (
    LIBRARY,
    EffectTerm,
    LaggedChannel,
    NonlinearParam,
    offset_through_play,
    play_gaps,
    step_through_play,
    warm_up_effects,
    windowed_design,
)
from afmdrift.model._evaluate import FIRST_SCORED_FRAME, MeasuredSeries, evaluate_series
from afmdrift.model._families import (
    CHANNEL_TAU_RANGE_S,
    ChannelResponse,
    DriftShape,
    EventResponse,
    GenericTerm,
    is_term_spec,
    parse_term_spec,
)
from afmdrift.model._feed import FeedBatch, HistoryFeed
from afmdrift.model._kalman import KalmanCAPredictor, KalmanPredictor
from afmdrift.model._physics import PhysicsPredictor, solve_wls
from afmdrift.model._positions import (
    commanded_offset_nm,
    drift_from_measurements,
    offset_change_nm,
    truth_frame_mean,
)
from afmdrift.model._reconstruct import (
    OffsetCurve,
    build_offset_curve,
    hermite_curve,
    reconstruct_offset,
    sinc_curve,
    sinc_reconstruct,
)
from afmdrift.model._registry import PREDICTOR_NAMES, make_predictor
from afmdrift.model._terms import (
    ENTRY_POINT_GROUP,
    available_terms,
    load_term_class,
    make_term,
    resolve_terms,
    term_class,
)
from afmdrift.model._trajectory import (
    BandConstraint,
    DriftTrajectory,
    FrameTrajectory,
    default_q,
)

if TYPE_CHECKING:
    from afmdrift.model._nn import NNPredictor, NNSeriesModel

__all__ = [
    "CHANNEL_TAU_RANGE_S",
    "ENTRY_POINT_GROUP",
    "FIRST_SCORED_FRAME",
    "LIBRARY",
    "PREDICTOR_NAMES",
    "BandConstraint",
    "ChannelResponse",
    "ConstantVelocityPredictor",
    "DriftShape",
    "DriftTrajectory",
    "EffectTerm",
    "EventResponse",
    "FeedBatch",
    "FrameTrajectory",
    "GenericTerm",
    "History",
    "HistoryFeed",
    "KalmanCAPredictor",
    "KalmanConfig",
    "KalmanPredictor",
    "LaggedChannel",
    "LastValuePredictor",
    "MeasuredSeries",
    "ModelConfig",
    "NNConfig",
    "NNPredictor",
    "NNSeriesModel",
    "NonlinearParam",
    "Observation",
    "OffsetCurve",
    "OffsetPlay",
    "PhysicsConfig",
    "PhysicsPredictor",
    "Prediction",
    "Predictor",
    "available_terms",
    "build_offset_curve",
    "commanded_offset_nm",
    "default_q",
    "drift_from_measurements",
    "evaluate_series",
    "events_of_kind",
    "hermite_curve",
    "is_term_spec",
    "load_term_class",
    "make_predictor",
    "make_term",
    "offset_change_nm",
    "offset_through_play",
    "parse_term_spec",
    "play_gaps",
    "reconstruct_offset",
    "resolve_terms",
    "scan_samples",
    "sinc_curve",
    "sinc_reconstruct",
    "solve_wls",
    "step_through_play",
    "term_class",
    "truth_frame_mean",
    "warm_up_effects",
    "windowed_design",
]


def __getattr__(name: str) -> Any:
    if name in ("NNPredictor", "NNSeriesModel"):
        from afmdrift.model import _nn

        return getattr(_nn, name)
    raise AttributeError(f"module 'afmdrift.model' has no attribute {name!r}")

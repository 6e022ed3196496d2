"""Drift prediction and reconstruction of the continuous offset d(t)."""

from afmdrift.model._base import History, Observation, Prediction, Predictor

__all__ = ["History", "Observation", "Prediction", "Predictor"]

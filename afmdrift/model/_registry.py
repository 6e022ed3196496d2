"""Predictors by name, for the configuration and the command line.

``make_predictor("physics", config)`` builds a predictor from the ``[model]``
section. Names:

================== ==========================================================
``last_value``     p̂ = last measured position
``constant_velocity`` linear extrapolation of the last two positions
``kalman``         Kalman filter, constant velocity, ML noise (Mokaberi 2006)
``kalman_ca``      the same with constant acceleration
``nn``             the paper's neural network (torch, imported on first use)
``physics``        sum of library effect terms, residual per config
``physics_nn``     the physics model with the paper's NN on the residual
================== ==========================================================
"""

from __future__ import annotations

from collections.abc import Callable

from afmdrift.config import ModelConfig
from afmdrift.errors import ConfigError
from afmdrift.model._base import Predictor
from afmdrift.model._baselines import ConstantVelocityPredictor, LastValuePredictor
from afmdrift.model._kalman import KalmanCAPredictor, KalmanPredictor
from afmdrift.model._physics import PhysicsNNPredictor, PhysicsPredictor

__all__ = ["PREDICTOR_NAMES", "make_predictor"]


def _last_value(cfg: ModelConfig) -> Predictor:

    return LastValuePredictor()


def _constant_velocity(cfg: ModelConfig) -> Predictor:

    return ConstantVelocityPredictor()


def _kalman(cfg: ModelConfig) -> Predictor:

    return KalmanPredictor(motion=cfg.kalman.motion, window=cfg.kalman.window)


def _kalman_ca(cfg: ModelConfig) -> Predictor:

    return KalmanCAPredictor(window=cfg.kalman.window)


def _nn(cfg: ModelConfig) -> Predictor:
    from afmdrift.model._nn import NNPredictor

    return NNPredictor(cfg.nn)


def _physics(cfg: ModelConfig) -> Predictor:

    return PhysicsPredictor(cfg.physics, nn_config=cfg.nn)


def _physics_nn(cfg: ModelConfig) -> Predictor:

    return PhysicsNNPredictor(cfg.physics, nn_config=cfg.nn)


_FACTORIES: dict[str, Callable[[ModelConfig], Predictor]] = {
    "last_value": _last_value,
    "constant_velocity": _constant_velocity,
    "kalman": _kalman,
    "kalman_ca": _kalman_ca,
    "nn": _nn,
    "physics": _physics,
    "physics_nn": _physics_nn,
}

#: Every predictor name ``make_predictor`` accepts.
PREDICTOR_NAMES: tuple[str, ...] = tuple(_FACTORIES)


def make_predictor(name: str, config: ModelConfig | None = None) -> Predictor:
    """A fresh predictor called ``name`` configured from ``config`` (default config if None).

    Raises
    ------
    ConfigError
        For an unknown name (the message lists the known ones).
    """
    factory = _FACTORIES.get(name)
    if factory is None:
        raise ConfigError(f"unknown predictor {name!r} (known: {', '.join(PREDICTOR_NAMES)})")
    return factory(config or ModelConfig())

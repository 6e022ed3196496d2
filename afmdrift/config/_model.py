"""Configuration of the drift models and the offset reconstruction (``[model]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["KalmanConfig", "ModelConfig", "NNConfig", "PhysicsConfig"]


class NNConfig(BaseModel):
    """The paper's neural network (Yang et al. 2008, section IV)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    lags: int = Field(8, ge=1, le=64, description="Past drift increments per input (N).")
    hidden: int = Field(50, ge=1, le=1000, description="tanh hidden units.")
    channels: list[str] = Field(
        default_factory=lambda: ["temperature_c"],
        description="Logged channels added to the input (value at the last frame).",
    )
    joint: bool = Field(False, description="One net for x and y (else one per axis).")
    initial_points: int = Field(
        20, ge=3, le=10000, description="Drift points collected before the first LM fit."
    )
    window: int = Field(50, ge=2, le=10000, description="Most recent training pairs online.")
    initial_iterations: int = Field(200, ge=1, le=10000, description="LM iterations, first fit.")
    online_iterations: int = Field(3, ge=1, le=1000, description="LM iterations per frame.")
    damping: float = Field(1e-2, gt=0, le=1e6, description="Initial LM damping λ.")
    seed: int = Field(0, ge=0, description="torch seed for the initial weights.")
    threads: int = Field(1, ge=1, le=64, description="torch threads while training.")


class KalmanConfig(BaseModel):
    """Kalman filter baseline after Mokaberi & Requicha (IEEE T-ASE 2006)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    motion: Literal["velocity", "acceleration"] = Field(
        "velocity", description="Constant-velocity or constant-acceleration state model."
    )
    window: int = Field(50, ge=5, le=10000, description="Recent points for the noise likelihood.")


class PhysicsConfig(BaseModel):
    """Physics-informed model: a sum of terms from the effects library."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    terms: list[str] = Field(
        default_factory=lambda: ["trend", "warmup", "thermal_lag", "creep", "scan_direction"],
        description="Effect terms (library names, entry points or plugin names).",
    )
    plugins: list[str] = Field(
        default_factory=list, description="Extra terms as 'package.module:Class'."
    )
    residual: Literal["none", "ar1", "nn"] = Field(
        "ar1", description="Model of what the terms leave: none, AR(1), or the paper's NN."
    )
    memory_s: float = Field(
        7200.0, ge=0, description="Exponential forgetting time of old points, s (0: keep all)."
    )
    max_points: int = Field(
        2000, ge=10, le=1_000_000, description="Most recent observations used by each fit."
    )
    sigma_floor_nm: float = Field(
        0.1, gt=0, le=100, description="Smallest per-point uncertainty used as weight."
    )
    min_points_per_column: float = Field(
        2.0, ge=1, le=20, description="A term enters once there are this many points per column."
    )
    refine_passes: int = Field(2, ge=1, le=10, description="Coordinate passes over θ.")
    search_growth: float = Field(
        0.1,
        ge=0,
        le=10,
        description="θ is searched again once the fitted points grew by this fraction since "
        "its last search (in between, only the linear coefficients are refitted); "
        "0 searches at every frame.",
    )


class ModelConfig(BaseModel):
    """``[model]``: which predictor the service uses and how d(t) is built."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    predictor: str = Field("physics", description="Predictor used by the service.")
    evaluate: list[str] = Field(
        default_factory=lambda: [
            "last_value",
            "constant_velocity",
            "kalman",
            "kalman_ca",
            "nn",
            "physics",
            "physics_nn",
        ],
        description="Predictors run side by side by `afmdrift evaluate`.",
    )
    reconstruction: Literal["hermite", "sinc"] = Field(
        "hermite", description="Continuous offset: causal cubic Hermite or the paper's sinc."
    )
    lookahead: int = Field(
        2, ge=1, le=16, description="Predicted future samples in each published curve."
    )
    blend_fraction: float = Field(
        0.1,
        ge=0,
        le=1,
        description="Hermite: hand over to the new prediction within this fraction of a frame "
        "period after publication (0: at the next frame time).",
    )
    trajectory_q: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="Drift trajectory: velocity diffusion q of the integrated random-walk "
        "prior, nm^2/s^3 (larger follows faster changes of the drift speed). Default: "
        "1e-5 x (128 s / scan time of the first frame)^2 (model/_trajectory.py).",
    )
    trajectory_window: int = Field(
        4,
        ge=2,
        le=64,
        description="Drift trajectory: newest frames kept free (re-solved) in causal mode; "
        "older ones are marginalised.",
    )
    nn: NNConfig = Field(default_factory=NNConfig)
    kalman: KalmanConfig = Field(default_factory=KalmanConfig)
    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)

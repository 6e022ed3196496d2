"""Configuration of the block phase-correlation engine (``[registration]``)."""

from __future__ import annotations

from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["RegistrationConfig"]


class RegistrationConfig(BaseModel):
    """Parameters of :func:`afmdrift.registration.measure_drift`.

    Defaults follow Yang, Jagannathan & Bohannan (IEEE T-NANO 2008): 64×64
    blocks extended to 128×128, horizontal gradient, several candidate peaks
    verified by MSE.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    block_size: int = Field(64, ge=8, le=1024, description="Block edge in px.")
    extended_size: int = Field(128, ge=16, le=2048, description="Extended block edge in px.")
    gradient: Literal["x", "y", "both", "none"] = Field(
        "x", description="Gradient image of eq. (2): along x (fast axis), y, both, or none."
    )
    peaks: int = Field(4, ge=1, le=32, description="Candidate peaks verified by MSE (K).")
    max_shift_px: float | None = Field(
        None, gt=0, description="Largest accepted shift; default (extended - block) / 2."
    )
    outlier_rule: Literal["mad", "paper"] = Field(
        "mad", description="Robust iterated median/MAD, or the paper's epsilon-from-mean."
    )
    epsilon_px: float = Field(2.0, gt=0, le=64, description="Paper rule: distance from mean.")
    mad_threshold: float = Field(3.5, gt=0, le=20, description="Robust z-score cut-off.")
    min_valid_blocks: int = Field(3, ge=1, le=4096, description="Fewer valid blocks: invalid.")
    reference: Literal["consecutive", "keyframe"] = Field(
        "keyframe", description="Measure against the previous frame or against a keyframe."
    )
    keyframe_min_overlap: float = Field(
        0.6, gt=0, lt=1, description="Re-anchor the keyframe when overlap falls below this."
    )
    threads: int = Field(1, ge=1, le=64, description="FFTW threads.")

    @model_validator(mode="after")
    def _check_sizes(self) -> Self:
        if self.extended_size < self.block_size:
            raise ValueError(
                f"extended_size ({self.extended_size}) must be >= block_size ({self.block_size})"
            )
        return self

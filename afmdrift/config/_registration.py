"""Configuration of the block phase-correlation engine (``[registration]``)."""

from __future__ import annotations

from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["RegistrationConfig"]

#: auto_block_size: extended windows the smaller edge must hold, and the smallest block
#: (smaller blocks hold too little of a particle texture: 0.27 px error on 128² frames
#: of 30 nm particles at 2 nm/px with 16/32 blocks). Frames under 160 px keep the
#: engine's own small-frame layout (windows of two thirds of the frame): with 32/64
#: blocks a 128² frame scanned across an offset move was placed 9 nm off. Between
#: 160 and 191 px the small-frame layout's heavily overlapping blocks understate σ
#: by about 2× (HS-AFM crops of 176 px: 57–67 % of errors within 2σ).
AUTO_WINDOWS = 2
AUTO_SMALLEST_BLOCK = 32
#: ... and the halved blocks it must hold along the smaller edge.
AUTO_MIN_BLOCKS = 5


class RegistrationConfig(BaseModel):
    """Parameters of :func:`afmdrift.registration.measure_drift`.

    Defaults follow Yang, Jagannathan & Bohannan (IEEE T-NANO 2008): 64×64
    blocks extended to 128×128, horizontal gradient, several candidate peaks
    verified by MSE.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    block_size: int = Field(64, ge=8, le=1024, description="Block edge in px.")
    auto_block_size: bool = Field(
        True,
        description="Halve block_size and extended_size (down to a 32 px block) while "
        "the frame's smaller edge holds no more than two extended windows but at least "
        "five halved blocks: 160-256 px frames get 32/64 blocks; smaller frames keep "
        "the windows of two thirds of the frame (see docs/registration.md).",
    )
    extended_size: int = Field(128, ge=16, le=2048, description="Extended block edge in px.")
    gradient: Literal["auto", "x", "y", "both", "none", "levelled"] = Field(
        "auto",
        description="Pre-filter: the gradient image of eq. (2) along x (fast axis), y, "
        "both, none (heights), levelled (heights less a line per scan line), or auto: x "
        "unless the x gradient's signal is below 8 % of its noise, then levelled.",
    )
    peaks: int = Field(4, ge=1, le=32, description="Candidate peaks verified by MSE (K).")
    block_search_px: float | None = Field(
        None,
        gt=0,
        description="Half-width of each block's peak search around its prior, px; default "
        "(extended - block) / 2 (at most extended / 2 - 2).",
    )
    max_shift_px: float | None = Field(
        None,
        gt=0,
        le=100_000,
        description="Largest drift between a frame and the reference it is registered on "
        "that is possible, px per axis (a stated bound, like suite2p's maxregshift): "
        "lattice translations beyond it are excluded, so on a periodic sample a bound "
        "under half a period decides which translation it is, and a result beyond it is "
        "refused. Default: no bound.",
    )
    lattice: Literal["track", "equivalent"] = Field(
        "track",
        description="On a periodic sample whose lattice translations the frames cannot "
        "tell apart: track (the drift is wanted: the prior or max_shift_px decides, else "
        "the pair is refused as ambiguous) or equivalent (the frames are to be registered "
        "and any lattice-equivalent shift registers them as well: the translation nearest "
        "the prior, or zero, is taken and the result says decided_by: equivalent; never "
        "for tracking drift).",
    )
    outlier_rule: Literal["mad", "paper"] = Field(
        "mad", description="Robust iterated median/MAD, or the paper's epsilon-from-mean."
    )
    epsilon_px: float = Field(2.0, gt=0, le=64, description="Paper rule: distance from mean.")
    mad_threshold: float = Field(3.5, gt=0, le=20, description="Robust z-score cut-off.")
    min_valid_fraction: float = Field(
        0.25,
        ge=0,
        le=1,
        description="Fewer valid blocks than this fraction of the blocks in the overlap: "
        "invalid (a few overlapping windows can agree on a false peak).",
    )
    max_block_spread_px: float = Field(
        2.0,
        gt=0,
        le=64,
        description="Valid blocks must agree: a larger per-axis standard deviation makes "
        "the frame invalid.",
    )
    min_valid_blocks: int = Field(
        3, ge=2, le=4096, description="Fewer valid blocks: invalid (two give an uncertainty)."
    )
    reference: Literal["consecutive", "keyframe"] = Field(
        "keyframe", description="Measure against the previous frame or against a keyframe."
    )
    keyframe_min_overlap: float = Field(
        0.6,
        gt=0,
        lt=1,
        description="Re-anchor the keyframe when the overlap (shared area, or share of "
        "blocks whose windows still fit) falls below this.",
    )
    subpixel: Literal["dft", "sinc", "parabolic", "gaussian"] = Field(
        "dft",
        description="Sub-pixel method: continuous maximum of the DFT-interpolated "
        "correlation (dft), or a 3-point peak model (see docs/registration.md).",
    )
    subpixel_band: float = Field(
        0.25, gt=0, le=1, description="dft method: frequencies used, as a fraction of Nyquist."
    )
    window_response: bool = Field(
        True,
        description="dft method: measure each reference block's response to its content "
        "moving under its window and divide it out (two extra block passes per reference: "
        "on re-anchoring with keyframes, on every frame with reference = consecutive; "
        "docs/registration.md).",
    )
    eps_rel: float = Field(
        1e-4,
        gt=0,
        le=1,
        description="Spectrum magnitude floor relative to each block's max (above the "
        "rounding noise of float32 FFTs, which whitening would otherwise amplify).",
    )
    coarse: bool = Field(
        True, description="Whole-frame coarse alignment when no expected drift is known."
    )
    coarse_search_px: float = Field(
        6.0,
        ge=1,
        le=1022,
        description="Block search half-width (px) around a trusted coarse prior (capped at "
        "block_search_px): on periodic samples a wider search lets blocks lock onto "
        "different lattice peaks.",
    )
    refine: bool = Field(
        True, description="Second block pass when the drift is over 2 px off the prior."
    )
    mse_stride_px: int = Field(
        4, ge=1, le=8, description="Lattice step of the MSE peak verification."
    )
    threads: int = Field(
        2,
        ge=1,
        le=64,
        description="Threads for the per-frame block work (they take batches of blocks in "
        "turn; results do not depend on it). Default 2: the cores of the reference machine.",
    )
    fftw_planner: Literal["estimate", "measure", "patient"] = Field(
        "measure", description="FFTW planner effort (plans are made once per shape)."
    )
    fftw_wisdom: str | None = Field(
        None,
        description="FFTW wisdom file; default $AFMDRIFT_FFTW_WISDOM or "
        "$XDG_CACHE_HOME/afmdrift/fftw-wisdom-<pyfftw version>; empty string disables.",
    )

    def for_shape(self, shape: tuple[int, int]) -> RegistrationConfig:
        """The configuration an image of ``shape`` (rows, cols) is measured with:
        this one, with the block sizes halved as ``auto_block_size`` says."""
        if not self.auto_block_size:
            return self
        edge = min(shape)
        block, ext = self.block_size, self.extended_size
        while (
            edge <= AUTO_WINDOWS * ext
            and edge >= AUTO_MIN_BLOCKS * (block // 2)
            and block >= 2 * AUTO_SMALLEST_BLOCK
        ):
            block, ext = block // 2, max(ext // 2, block // 2)
        if block == self.block_size:
            return self
        update: dict[str, object] = {"block_size": block, "extended_size": ext}
        if self.block_search_px is not None:
            update["block_search_px"] = min(self.block_search_px, ext / 2 - 2)
        return self.model_copy(update=update)

    @model_validator(mode="after")
    def _check_sizes(self) -> Self:
        if self.extended_size < self.block_size:
            raise ValueError(
                f"extended_size ({self.extended_size}) must be >= block_size ({self.block_size})"
            )
        if self.block_search_px is not None and self.block_search_px > self.extended_size / 2 - 2:
            raise ValueError(
                f"block_search_px ({self.block_search_px}) must be <= extended_size / 2 - 2 "
                f"({self.extended_size / 2 - 2:g})"
            )
        return self

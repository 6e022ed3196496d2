"""What the per-frame pipeline produces: one record per frame, and what a restart needs.

:class:`FrameRecord` is one row of the run store and of ``measurements.csv``
(columns in docs/service.md); :class:`ResumeState` is what a restarted service
reads back from the store to continue.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.model import Observation
from afmdrift.records import ScanDirection

__all__ = [
    "FRAME_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "FrameRecord",
    "ResumeState",
    "measurement_row",
    "observation_from_record",
    "record_from_row",
    "reference_direction_of",
]


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """Everything the service knows about one processed frame (one store row).

    ``seq`` numbers frames as the service saw them (0, 1, 2, ...);
    ``instrument_frame`` is the instrument's own index. Measured values are
    NaN when the measurement failed or the frame is the reference.
    """

    seq: int
    instrument_frame: int
    epoch: int
    t_start_s: float
    t_end_s: float
    t_mid_s: float
    direction: str
    rows: int
    cols: int
    pixel_x_nm: float
    pixel_y_nm: float
    dx_nm: float
    dy_nm: float
    image_x_nm: float
    image_y_nm: float
    x_nm: float
    y_nm: float
    sigma_nm: float
    valid: bool
    fed_model: bool
    reason: str
    valid_blocks: int
    total_blocks: int
    keyframe_index: int
    reanchored: bool
    pred_x_nm: float
    pred_y_nm: float
    pred_sigma_nm: float
    offset_x_nm: float
    offset_y_nm: float
    wall_s: float
    latency_s: float
    field_json: str
    #: The observation the frame gave the model (its latest trajectory
    #: sample; NaN when it fed nothing, or in a store written before them).
    obs_t_s: float = math.nan
    obs_x_nm: float = math.nan
    obs_y_nm: float = math.nan
    obs_sigma_nm: float = math.nan

    @property
    def resid_x_nm(self) -> float:
        return self.x_nm - self.pred_x_nm

    @property
    def resid_y_nm(self) -> float:
        return self.y_nm - self.pred_y_nm

    @property
    def pred_error_nm(self) -> float:
        """Distance between the prediction and the measured position (NaN if either is)."""
        return math.hypot(self.resid_x_nm, self.resid_y_nm)


#: Columns of ``measurements.csv`` (see docs/service.md).
MEASUREMENT_COLUMNS: tuple[str, ...] = (
    "frame",
    "t_s",
    "dx_nm",
    "dy_nm",
    "x_nm",
    "y_nm",
    "sigma_nm",
    "valid_blocks",
    "pred_x_nm",
    "pred_y_nm",
    "total_blocks",
    "valid",
    "fed_model",
    "image_x_nm",
    "image_y_nm",
    "offset_x_nm",
    "offset_y_nm",
    "pred_sigma_nm",
    "pred_error_nm",
    "reason",
)


@dataclass(frozen=True, slots=True)
class ResumeState:
    """What a restarted service needs from the store."""

    last: FrameRecord
    predictor: str
    predictor_state: dict[str, Any] | None
    curve: dict[str, Any] | None
    reference: npt.NDArray[np.float32] | None
    reference_seq: int | None
    #: The stored reference's own frame record (its timing and drift position).
    reference_record: FrameRecord | None
    reference_x_nm: float
    reference_y_nm: float
    event_cursor: int
    epoch: int
    t_ref_s: float | None


def observation_from_record(
    r: FrameRecord, reference_direction: ScanDirection | None = None
) -> Observation:
    """The model observation that a frame which fed the model contributed
    (the mid-scan position for records written before ``obs_*`` existed);
    ``reference_direction`` is the scan direction of the session reference."""
    if math.isfinite(r.obs_t_s):
        return Observation(
            t_s=r.obs_t_s,
            x_nm=r.obs_x_nm,
            y_nm=r.obs_y_nm,
            sigma_nm=r.obs_sigma_nm if math.isfinite(r.obs_sigma_nm) else 0.0,
            direction=ScanDirection(r.direction),
            frame=r.seq,
            reference_direction=reference_direction,
        )
    return Observation(
        t_s=r.t_mid_s,
        x_nm=r.x_nm,
        y_nm=r.y_nm,
        sigma_nm=r.sigma_nm if math.isfinite(r.sigma_nm) else 0.0,
        direction=ScanDirection(r.direction),
        frame=r.seq,
        reference_direction=reference_direction,
    )


def reference_direction_of(records: Sequence[FrameRecord]) -> ScanDirection | None:
    """Scan direction of the session reference among ``records`` (None if absent)."""
    for r in records:
        if r.reason == "reference":
            return ScanDirection(r.direction)
    return None


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return str(v)


def measurement_row(r: FrameRecord) -> list[str]:
    """The ``measurements.csv`` row of ``r`` (columns :data:`MEASUREMENT_COLUMNS`)."""
    values = asdict(r)
    values["frame"] = r.seq
    values["t_s"] = r.t_mid_s
    values["pred_error_nm"] = r.pred_error_nm
    return [_fmt(values[c]) for c in MEASUREMENT_COLUMNS]


#: Columns of a stored frame row, in :class:`FrameRecord` field order (the run
#: store's ``frames`` table, docs/service.md).
FRAME_COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(FrameRecord))


def record_from_row(row: Sequence[Any]) -> FrameRecord:
    """A :class:`FrameRecord` from a stored row in :data:`FRAME_COLUMNS` order
    (SQL NULL floats become NaN, integers 0/1 booleans)."""
    values: dict[str, Any] = {}
    for f, v in zip(fields(FrameRecord), row, strict=True):
        if f.type == "bool":
            values[f.name] = bool(v)
        elif f.type == "float":
            values[f.name] = math.nan if v is None else float(v)
        else:
            values[f.name] = v
    return FrameRecord(**values)

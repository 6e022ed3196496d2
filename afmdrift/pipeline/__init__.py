"""The per-frame pipeline: from a frame to a drift position, a prediction and d(t).

Between the model and the service: the daemon, ``afmdrift replay`` and
``afmdrift diagnose`` run every frame through :class:`FramePipeline` (its
stages are listed in :meth:`FramePipeline.process`), and the run store keeps
the :class:`FrameRecord` it produces.
"""

from afmdrift.pipeline._frame import FrameOutcome, FramePipeline
from afmdrift.pipeline._positions import DriftPositions, FramePosition, summarise_field
from afmdrift.pipeline._records import (
    FRAME_COLUMNS,
    MEASUREMENT_COLUMNS,
    FrameRecord,
    ResumeState,
    measurement_row,
    observation_from_record,
    record_from_row,
)

__all__ = [
    "FRAME_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "DriftPositions",
    "FrameOutcome",
    "FramePipeline",
    "FramePosition",
    "FrameRecord",
    "ResumeState",
    "measurement_row",
    "observation_from_record",
    "record_from_row",
    "summarise_field",
]

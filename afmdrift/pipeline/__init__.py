"""The per-frame pipeline: from a frame to a drift position, a prediction and d(t).

Between the model and the runs: the daemon calls :meth:`FramePipeline.process`
for each new frame, and every tool that holds a whole recording (``afmdrift
replay``, ``diagnose``, ``evaluate``, ``correct``, ``measure``, ``batch``)
iterates :meth:`FramePipeline.run`, which reads the recording one frame ahead
(the stages are listed in :meth:`FramePipeline.process`). The run store
(:mod:`afmdrift.runs`) keeps the :class:`FrameRecord` it produces.
"""

from afmdrift.pipeline._dewarp import dewarp_frame, image_positions
from afmdrift.pipeline._frame import (
    MIN_HANDOVER_STEP_NM,
    FrameOutcome,
    FramePipeline,
    Handover,
    largest_step_nm,
)
from afmdrift.pipeline._positions import DriftPositions, FramePosition, summarise_field
from afmdrift.pipeline._records import (
    FRAME_COLUMNS,
    MEASUREMENT_COLUMNS,
    FrameRecord,
    ResumeState,
    measurement_row,
    observation_from_record,
    record_from_row,
    reference_direction_of,
)

__all__ = [
    "FRAME_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "MIN_HANDOVER_STEP_NM",
    "DriftPositions",
    "FrameOutcome",
    "FramePipeline",
    "FramePosition",
    "FrameRecord",
    "Handover",
    "ResumeState",
    "dewarp_frame",
    "image_positions",
    "largest_step_nm",
    "measurement_row",
    "observation_from_record",
    "record_from_row",
    "reference_direction_of",
    "summarise_field",
]

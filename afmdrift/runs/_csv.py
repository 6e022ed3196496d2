"""The CSV files of a run directory, for users to open while the run goes on.

``measurements.csv`` (one row per frame, columns
:data:`~afmdrift.pipeline.MEASUREMENT_COLUMNS`) and ``trajectory.csv`` /
``trajectory_smoothed.csv`` (the drift trajectory's samples, columns
:data:`TRAJECTORY_COLUMNS`); both are described in ``docs/service.md``. The
run store's tables stay the record; these files are views of it.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

from afmdrift.model import FrameTrajectory
from afmdrift.pipeline import MEASUREMENT_COLUMNS, FrameRecord, measurement_row

__all__ = [
    "TRAJECTORY_COLUMNS",
    "trajectory_rows",
    "write_measurements_csv",
    "write_trajectory_csv",
]

#: Columns of ``trajectory.csv`` (docs/service.md).
TRAJECTORY_COLUMNS = ("t_s", "x_nm", "y_nm", "sigma_x_nm", "sigma_y_nm", "frame")


def trajectory_rows(seq: int, trajectory: FrameTrajectory) -> list[tuple[float, ...]]:
    """``trajectory.csv`` rows of one frame's samples (columns :data:`TRAJECTORY_COLUMNS`)."""
    return [
        (
            float(trajectory.t_s[k]),
            float(trajectory.xy_nm[k, 0]),
            float(trajectory.xy_nm[k, 1]),
            float(trajectory.sigma_nm[k, 0]),
            float(trajectory.sigma_nm[k, 1]),
            seq,
        )
        for k in range(trajectory.t_s.size)
    ]


def write_trajectory_csv(
    path: str | Path, rows: Iterable[tuple[float, ...]], *, append: bool = False
) -> Path:
    """Write (or append) ``trajectory.csv`` rows; a new file gets the header."""
    out = Path(path)
    new = not append or not out.exists()
    with out.open("w" if not append else "a", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        if new:
            w.writerow(TRAJECTORY_COLUMNS)
        for r in rows:
            w.writerow([repr(v) if isinstance(v, float) else v for v in r])
    return out


def write_measurements_csv(path: Path, records: Iterable[FrameRecord]) -> Path:
    """Write ``measurements.csv`` (columns :data:`MEASUREMENT_COLUMNS`) atomically."""
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(MEASUREMENT_COLUMNS)
        for r in records:
            w.writerow(measurement_row(r))
    tmp.replace(path)
    return path

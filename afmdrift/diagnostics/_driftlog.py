"""A drift log (positions without images, :mod:`afmdrift.session._driftlog`)
as the diagnostics' measurement table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmdrift.diagnostics._data import RunData
from afmdrift.records import ScanDirection
from afmdrift.session import read_drift_log

__all__ = ["load_drift_log"]


def load_drift_log(path: str | Path) -> RunData:
    """The measurement table of a drift log folder: each frame's position as the
    log gives it (frames without one did not feed the model), with its
    channels, events and, where the log has it, the true drift."""
    log = read_drift_log(path)
    fed = np.all(np.isfinite(log.xy_nm), axis=1)
    sigma = np.where(np.isfinite(log.sigma_nm), log.sigma_nm, 0.0)
    truth = log.truth
    return RunData(
        frame=np.arange(len(log), dtype=np.int64),
        t_s=log.t_s.copy(),
        t_end_s=log.frame_times[:, 1].copy(),
        xy_nm=log.xy_nm.copy(),
        sigma_nm=sigma,
        scan_sign=np.array([1.0 if d is ScanDirection.UP else -1.0 for d in log.directions]),
        fed=fed,
        channels=log.channel_samples(),
        events=list(log.events),
        truth_t_s=None if truth is None else truth[:, 0].copy(),
        truth_nm=None if truth is None else truth[:, 1:3].copy(),
        session_dir=None,
        run_dir=Path(path),
        window_s=log.frame_times.copy(),
    )

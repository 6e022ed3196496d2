"""Drift logs: measured positions over time, with a lab's sensor and event logs,
and no images.

Many users have drift records made elsewhere: positions from Nanonis atom
tracking, from another registration tool, or a closed loop's corrections. A
drift log folder holds them in the session format's CSV dialect
(``docs/session-format.md``, *Drift logs*)::

    positions.csv   t_s, x_nm, y_nm [, frame, sigma_nm, direction, t_start_s, t_end_s]
    frames.csv      frame, t_start_s, t_end_s [, direction]       (optional)
    channels.csv    t_s, one column per channel                   (optional)
    events.csv      t_s, kind [, x_nm, y_nm]                      (optional)
    truth.csv       t_s, x_nm, y_nm                               (optional)

``afmdrift diagnose DIR`` and ``afmdrift evaluate DIR`` take such a folder as
they take a session directory. Positions are drift positions p: commanded
offset moves removed, relative to the first position's reference, x along the
fast scan axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.records import ChannelSample, Event, ScanDirection
from afmdrift.session._format import (
    SessionError,
    _read_channels,
    _read_csv,
    _read_events,
    _read_truth,
    _to_float,
    _to_int,
    read_frame_windows,
    scan_direction,
)

__all__ = ["POSITIONS_FILE", "DriftLog", "is_drift_log", "read_drift_log"]

FloatArray = npt.NDArray[np.float64]

#: The file that makes a folder a drift log.
POSITIONS_FILE = "positions.csv"


def is_drift_log(path: str | Path) -> bool:
    """True if ``path`` is a folder with ``positions.csv`` (and not a session)."""
    p = Path(path)
    return (p / POSITIONS_FILE).is_file() and not (p / "session.json").is_file()


@dataclass(frozen=True, slots=True)
class DriftLog:
    """A drift record without images, one entry per frame (or per position when
    there are no frames).

    Attributes
    ----------
    path : Path
    frame_times : ndarray, shape (n, 2)
        Scan window ``(t_start_s, t_end_s)`` of each frame; a position without
        a window is a point, ``t_start_s == t_end_s``.
    directions : list of ScanDirection
        Slow-scan direction of each frame (``up`` where unknown).
    t_s : ndarray, shape (n,)
        Time of each frame's position, s (its window's middle where it has none).
    xy_nm : ndarray, shape (n, 2)
        Drift position p; NaN for a frame without a position (refused).
    sigma_nm : ndarray, shape (n,)
        Uncertainty of each coordinate, nm (NaN where unknown).
    channel_t_s, channels, events, truth
        As in :class:`~afmdrift.session.Session`.
    """

    path: Path
    frame_times: FloatArray
    directions: list[ScanDirection]
    t_s: FloatArray
    xy_nm: FloatArray
    sigma_nm: FloatArray
    channel_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    channels: dict[str, FloatArray] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    truth: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.frame_times.shape[0])

    def channel_samples(self) -> list[ChannelSample]:
        names = list(self.channels)
        return [
            ChannelSample(t_s=float(t), values={n: float(self.channels[n][k]) for n in names})
            for k, t in enumerate(self.channel_t_s)
        ]


def read_drift_log(path: str | Path) -> DriftLog:
    """Read a drift log folder (see the module docstring).

    Raises
    ------
    SessionError
        ``positions.csv`` is missing, a required column or value is missing or
        malformed (the message names the file and line), times decrease, or a
        position names a frame that ``frames.csv`` does not have.
    """
    root = Path(path)
    pos_path = root / POSITIONS_FILE
    if not pos_path.is_file():
        raise SessionError(f"{pos_path}: missing (a drift log needs positions.csv)")
    rows = _read_csv(pos_path, ["t_s", "x_nm", "y_nm"])
    if len(rows) < 2:
        raise SessionError(f"{pos_path}: a drift log needs two positions or more")
    frames_csv = root / "frames.csv"
    frames = read_frame_windows(frames_csv, directions=False) if frames_csv.is_file() else None
    n = frames[0].shape[0] if frames is not None else len(rows)
    t = np.full(n, np.nan)
    xy = np.full((n, 2), np.nan)
    sigma = np.full(n, np.nan)
    window = np.full((n, 2), np.nan)
    directions = [ScanDirection.UP] * n
    given: set[int] = set()  # frames whose direction positions.csv gives
    for k, (line, row) in enumerate(rows):
        where = f"{pos_path}:{line}"
        i = k
        if frames is not None:
            if not row.get("frame"):
                raise SessionError(f"{where}: with frames.csv, each position names its frame")
            i = _to_int(row["frame"], where, "frame")
            if not 0 <= i < n:
                raise SessionError(f"{where}: frame {i} is not in frames.csv (0..{n - 1})")
        t[i] = _to_float(row["t_s"], where, "t_s")
        xy[i] = (_to_float(row["x_nm"], where, "x_nm"), _to_float(row["y_nm"], where, "y_nm"))
        if row.get("sigma_nm"):
            sigma[i] = _to_float(row["sigma_nm"], where, "sigma_nm")
        if row.get("direction"):
            directions[i] = scan_direction(row["direction"], where)
            given.add(i)
        if row.get("t_start_s") and row.get("t_end_s"):
            window[i] = (
                _to_float(row["t_start_s"], where, "t_start_s"),
                _to_float(row["t_end_s"], where, "t_end_s"),
            )
    if frames is not None:
        window, frame_dirs = frames
        for k, d in enumerate(frame_dirs):
            if d is None:
                continue
            if k in given and directions[k] is not d:
                raise SessionError(
                    f"{pos_path}: frame {k} is '{directions[k].value}' here but "
                    f"'{d.value}' in frames.csv"
                )
            directions[k] = d
    missing = ~np.isfinite(window[:, 0])
    window[missing] = t[missing, np.newaxis]
    t = np.where(np.isfinite(t), t, window.mean(axis=1))
    if not np.all(np.isfinite(window)) or np.any(np.diff(t) <= 0):
        raise SessionError(f"{pos_path}: times must be finite and increase from frame to frame")
    if np.any(window[:, 1] < window[:, 0]):
        raise SessionError(f"{pos_path}: a frame ends before it starts")
    if np.any(np.isfinite(sigma) & (sigma < 0)):
        raise SessionError(f"{pos_path}: sigma_nm must not be negative")
    channel_t, channels = _read_channels(root / "channels.csv")
    return DriftLog(
        path=root,
        frame_times=window,
        directions=directions,
        t_s=t,
        xy_nm=xy,
        sigma_nm=sigma,
        channel_t_s=channel_t,
        channels=channels,
        events=_read_events(root / "events.csv"),
        truth=_read_truth(root / "truth.csv"),
    )

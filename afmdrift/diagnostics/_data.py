"""The measurement table that the diagnostics read: one row per frame.

:class:`RunData` holds what the drift service measured on each frame (the
drift position p, its uncertainty, the scan direction), the logged channels
and events, and, for simulated sessions, the true drift. It is built from a
run directory written by ``afmdrift replay`` or the daemon
(:func:`load_run`), or directly from arrays (:meth:`RunData.from_arrays`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.errors import InputError
from afmdrift.model import History, HistoryFeed, Observation, scan_samples
from afmdrift.records import ChannelSample, Event, ScanDirection
from afmdrift.runs import DB_NAME, ModelChange, RunStore
from afmdrift.session import read_session

__all__ = ["RunData", "load_run"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class RunData:
    """Per-frame drift measurements of one run, with its channels and events.

    Attributes
    ----------
    frame : ndarray of int, shape (n,)
        Frame sequence number.
    t_s : ndarray, shape (n,)
        Mid-scan time of each frame (the time of its measurement), s.
    t_end_s : ndarray, shape (n,)
        End of each frame's scan, s: channels and events up to this time are
        known when the frame is processed.
    xy_nm : ndarray, shape (n, 2)
        Measured drift position p (x, y), commanded offsets removed, nm; NaN
        where the measurement failed.
    sigma_nm : ndarray, shape (n,)
        Standard uncertainty of each coordinate, nm (0 where unknown).
    scan_sign : ndarray, shape (n,)
        +1 for up frames, −1 for down frames.
    fed : ndarray of bool, shape (n,)
        The frame fed the model (a valid, confident measurement).
    channels : list of ChannelSample
        Logged channels, in time order.
    events : list of Event
        Event log, in time order.
    truth_t_s, truth_nm : ndarray or None
        True drift (simulated sessions only), shapes (m,) and (m, 2).
    pixel_size_nm : tuple of float
        (x, y) pixel size of the frames, nm.
    session_dir, run_dir : Path or None
        Where the data came from.
    pred_nm : ndarray or None, shape (n, 2)
        The run's own one-step predictions (NaN where none was made).
    run_model : dict or None
        The ``[model]`` configuration the run used (JSON form).
    predictor_state : dict or None
        The run's predictor state after its last fed frame.
    curves : dict or None
        Published offset curves d(t) by frame number (JSON form).
    window_s : ndarray or None, shape (n, 2)
        Scan window ``(t_start_s, t_end_s)`` each position averages over (a
        whole frame's position is the mean of p over its lines); None or NaN
        rows: point measurements at ``t_s``.
    model_changes : list of ModelChange
        Where the run's model changed while it ran (``add_term``,
        ``remove_term``, ``reload_model``; ``docs/service.md``): its stored
        predictions before and after come from different models.
    """

    frame: npt.NDArray[np.int64]
    t_s: FloatArray
    t_end_s: FloatArray
    xy_nm: FloatArray
    sigma_nm: FloatArray
    scan_sign: FloatArray
    fed: npt.NDArray[np.bool_]
    channels: list[ChannelSample] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    truth_t_s: FloatArray | None = None
    truth_nm: FloatArray | None = None
    pixel_size_nm: tuple[float, float] = (1.0, 1.0)
    session_dir: Path | None = None
    run_dir: Path | None = None
    pred_nm: FloatArray | None = None
    run_model: dict[str, Any] | None = None
    predictor_state: dict[str, Any] | None = None
    curves: dict[int, dict[str, Any]] | None = None
    window_s: FloatArray | None = None
    model_changes: list[ModelChange] = field(default_factory=list)

    @classmethod
    def from_arrays(
        cls,
        *,
        t_s: npt.ArrayLike,
        xy_nm: npt.ArrayLike,
        scan_sign: npt.ArrayLike | None = None,
        sigma_nm: npt.ArrayLike | None = None,
        t_end_s: npt.ArrayLike | None = None,
        channels: Sequence[ChannelSample] = (),
        events: Sequence[Event] = (),
        truth_t_s: npt.ArrayLike | None = None,
        truth_nm: npt.ArrayLike | None = None,
    ) -> RunData:
        """Build a table from arrays (every frame valid and fed).

        Raises
        ------
        InputError
            If the shapes disagree, times are not increasing or fewer than
            two frames are given.
        """
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        xy = np.asarray(xy_nm, dtype=np.float64).reshape(-1, 2)
        n = t.size
        if xy.shape[0] != n:
            raise InputError(f"xy_nm has {xy.shape[0]} rows for {n} times")
        if n < 2 or np.any(np.diff(t) <= 0):
            raise InputError(f"need at least two frames with increasing t_s (got {n})")
        sign = np.ones(n) if scan_sign is None else np.asarray(scan_sign, dtype=np.float64)
        sig = np.zeros(n) if sigma_nm is None else np.asarray(sigma_nm, dtype=np.float64)
        t_end = t.copy() if t_end_s is None else np.asarray(t_end_s, dtype=np.float64)
        for name, arr in (("scan_sign", sign), ("sigma_nm", sig), ("t_end_s", t_end)):
            if arr.shape != (n,):
                raise InputError(f"{name} has shape {arr.shape}, expected ({n},)")
        return cls(
            frame=np.arange(n, dtype=np.int64),
            t_s=t,
            t_end_s=t_end,
            xy_nm=xy,
            sigma_nm=sig,
            scan_sign=sign,
            fed=np.all(np.isfinite(xy), axis=1),
            channels=sorted(channels, key=lambda c: c.t_s),
            events=sorted(events, key=lambda e: e.t_s),
            truth_t_s=None if truth_t_s is None else np.asarray(truth_t_s, dtype=np.float64),
            truth_nm=None
            if truth_nm is None
            else np.asarray(truth_nm, dtype=np.float64).reshape(-1, 2),
        )

    @property
    def n(self) -> int:
        return int(self.t_s.size)

    def observations(self) -> list[Observation]:
        """The frames that fed the model, as model observations (in time order)."""
        out = []
        for k in np.flatnonzero(self.fed):
            window = Observation.window_of(None if self.window_s is None else self.window_s[k])
            out.append(
                Observation(
                    t_s=float(self.t_s[k]),
                    x_nm=float(self.xy_nm[k, 0]),
                    y_nm=float(self.xy_nm[k, 1]),
                    sigma_nm=float(self.sigma_nm[k]),
                    direction=ScanDirection.UP if self.scan_sign[k] > 0 else ScanDirection.DOWN,
                    frame=int(self.frame[k]),
                    window_s=window,
                )
            )
        return out

    def samples(self, index: npt.ArrayLike | None = None) -> FloatArray:
        """Times at which a model is averaged to describe each position (n, m)
        (:func:`~afmdrift.model.scan_samples`), of the rows ``index`` (default: all)."""
        rows = np.arange(self.n) if index is None else np.asarray(index)
        window = None if self.window_s is None else self.window_s[rows]
        return scan_samples(self.t_s[rows], window)

    def history(self, *, until_s: float | None = None) -> History:
        """Channels and events logged up to ``until_s`` (default: all)."""
        feed = HistoryFeed(self.channels, self.events)
        feed.advance(math.inf if until_s is None else until_s)
        return feed.history

    def channel_names(self) -> list[str]:
        names: set[str] = set()
        for c in self.channels:
            names.update(c.values)
        return sorted(names)

    def channel_series(self, name: str) -> tuple[FloatArray, FloatArray]:
        """Times (m,) and values (m,) of one logged channel (finite values only)."""
        t = np.array([c.t_s for c in self.channels if name in c.values], dtype=np.float64)
        v = np.array([c.values[name] for c in self.channels if name in c.values], dtype=np.float64)
        ok = np.isfinite(v)
        return t[ok], v[ok]

    def truth_at(self, t_s: npt.ArrayLike) -> FloatArray | None:
        """True drift at ``t_s`` (linear interpolation), shape (n, 2), or None."""
        if self.truth_t_s is None or self.truth_nm is None:
            return None
        t = np.asarray(t_s, dtype=np.float64)
        return np.column_stack([np.interp(t, self.truth_t_s, self.truth_nm[:, a]) for a in (0, 1)])


def load_run(run_dir: str | Path, *, session_dir: str | Path | None = None) -> RunData:
    """Read a run directory (``run.sqlite`` written by replay or the daemon).

    Parameters
    ----------
    run_dir : path-like
        The run directory.
    session_dir : path-like, optional
        The session it was made from; its ``truth.csv`` (if any) is attached
        and its frames are used for the vector-field figure.

    Raises
    ------
    InputError
        If the directory holds no run store or fewer than two measured frames.
    """

    rd = Path(run_dir)
    if not (rd / DB_NAME).is_file():
        raise InputError(f"{rd}: no run store ({DB_NAME}); run `afmdrift replay` first")
    with RunStore(rd) as store:
        records = store.frames()
        channels = store.channels()
        events = [e for _, _, e in store.events()]
        resume = store.resume_state()
        meta = store.meta()
        changes = store.model_changes()
        curves = {}
        for r in records:
            c = store.curve(r.seq)
            if c is not None:
                curves[r.seq] = c
    run_model: dict[str, Any] | None = None
    if "config" in meta:
        try:
            run_model = json.loads(meta["config"]).get("model")
        except (json.JSONDecodeError, AttributeError):
            run_model = None
    if len(records) < 2:
        raise InputError(f"{rd}: the run has {len(records)} frame(s); need at least two")
    records = sorted(records, key=lambda r: r.seq)
    truth_t = truth = None
    sdir = Path(session_dir) if session_dir is not None else None
    if sdir is not None:
        s = read_session(sdir)
        if s.truth is not None:
            truth_t = np.asarray(s.truth[:, 0], dtype=np.float64)
            truth = np.asarray(s.truth[:, 1:3], dtype=np.float64)
    return RunData(
        frame=np.array([r.seq for r in records], dtype=np.int64),
        t_s=np.array([r.t_mid_s for r in records], dtype=np.float64),
        t_end_s=np.array([r.t_end_s for r in records], dtype=np.float64),
        xy_nm=np.array([[r.x_nm, r.y_nm] for r in records], dtype=np.float64),
        sigma_nm=np.array(
            [r.sigma_nm if np.isfinite(r.sigma_nm) else 0.0 for r in records], dtype=np.float64
        ),
        scan_sign=np.array([1.0 if r.direction == "up" else -1.0 for r in records]),
        fed=np.array([bool(r.fed_model) for r in records], dtype=bool),
        channels=sorted(channels, key=lambda c: c.t_s),
        events=sorted(events, key=lambda e: e.t_s),
        truth_t_s=truth_t,
        truth_nm=truth,
        pixel_size_nm=(float(records[-1].pixel_x_nm), float(records[-1].pixel_y_nm)),
        session_dir=sdir,
        run_dir=rd,
        pred_nm=np.array([[r.pred_x_nm, r.pred_y_nm] for r in records], dtype=np.float64),
        run_model=run_model,
        predictor_state=None if resume is None else resume.predictor_state,
        curves=curves,
        model_changes=changes,
    )

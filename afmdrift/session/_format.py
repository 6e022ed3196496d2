"""Session directory format v1: reading, validating and writing.

The format is documented for other tools in ``docs/session-format.md``::

    session.json   {"format": "afmdrift-session", "version": 1,
                    "pixel_size_nm": [px, py], "line_time_s": s, "fast_axis": "x",
                    "units": "nm", "start_time": ISO-8601, "source": text}
    frames.npy     (N, rows, cols) float32/float64 heights in nm
    frames.csv     frame,t_start_s,t_end_s,direction       (direction: up | down)
    channels.csv   t_s,<name>,...   optional; temperature_c, humidity_pct recognised
    events.csv     t_s,kind,x_nm,y_nm   optional; kinds offset_move, manipulation,
                   tip_change, power_on
    truth.csv      t_s,x_nm,y_nm   optional; true drift p(t), registration sign convention

Extra keys in ``session.json``, extra columns and extra files are accepted and
preserved where they have a place (``Session.extra``, extra channel columns).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift._bounded import loads_json, read_text
from afmdrift.errors import InputError
from afmdrift.records import ChannelSample, Event, Frame, ScanDirection, event_kind

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "PRIOR_KEY",
    "Session",
    "SessionError",
    "SessionMeta",
    "read_session",
    "session_prior_px",
    "write_session",
]

FORMAT_NAME = "afmdrift-session"
FORMAT_VERSION = 1
#: Limits of the reader: session.json size, each CSV file's size, and the
#: largest plausible pixel (an AFM scan of 100 µm over 16 px is 6 µm/px).
MAX_META_BYTES = 1 << 20
MAX_CSV_BYTES = 256 << 20
MAX_PIXEL_NM = 1e6

#: Files of a session directory that a session may lack (written only when it has them).
_OPTIONAL_FILES = (
    "channels.csv",
    "events.csv",
    "truth.csv",
    "truth_components.csv",
    "scenario.json",
)


class SessionError(InputError):
    """A session directory is missing a file or holds inconsistent data."""


@dataclass(frozen=True, slots=True)
class SessionMeta:
    """Contents of ``session.json``."""

    pixel_size_nm: tuple[float, float]
    line_time_s: float
    start_time: str
    source: str
    fast_axis: str = "x"
    units: str = "nm"
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = dict(self.extra)
        doc.update(
            {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "pixel_size_nm": [float(self.pixel_size_nm[0]), float(self.pixel_size_nm[1])],
                "line_time_s": float(self.line_time_s),
                "fast_axis": self.fast_axis,
                "units": self.units,
                "start_time": self.start_time,
                "source": self.source,
            }
        )
        return doc


#: The key of ``session.json`` under which ``afmdrift import --prior-px``
#: stores the expected drift of the first frame after the first, px.
PRIOR_KEY = "prior_px"


def session_prior_px(session: Session) -> tuple[float, float] | None:
    """The expected first drift stored with ``session`` (:data:`PRIOR_KEY`), px.

    Raises
    ------
    SessionError
        The stored value is not two finite numbers.
    """
    value = session.meta.extra.get(PRIOR_KEY)
    if value is None:
        return None
    try:
        dx, dy = (float(v) for v in value)
    except (TypeError, ValueError):
        raise SessionError(
            f"session.json: {PRIOR_KEY} must be [dx, dy] in px, got {value!r}"
        ) from None
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise SessionError(f"session.json: {PRIOR_KEY} must be finite, got {value!r}")
    return dx, dy


@dataclass(slots=True)
class Session:
    """A recorded or imported session held in memory.

    ``frames`` may be a read-only memory map. ``frame_times`` has one row per
    frame: ``(t_start_s, t_end_s)``; ``directions`` one entry per frame.
    ``channels`` maps column name to a float array sampled at ``channel_t_s``.
    ``truth`` is ``(t_s, x_nm, y_nm)`` as an (M, 3) array, or ``None``.
    """

    meta: SessionMeta
    frames: npt.NDArray[np.floating]
    frame_times: npt.NDArray[np.float64]
    directions: list[ScanDirection]
    channel_t_s: npt.NDArray[np.float64] = field(
        default_factory=lambda: np.zeros(0, dtype=np.float64)
    )
    channels: dict[str, npt.NDArray[np.float64]] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    truth: npt.NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        validate_session(self)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def frame(self, i: int) -> Frame:
        """Frame ``i`` as a driver record (heights are a view, not a copy)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range 0..{len(self) - 1}")
        t0, t1 = self.frame_times[i]
        return Frame(
            index=i,
            heights_nm=self.frames[i],
            pixel_size_nm=self.meta.pixel_size_nm,
            t_start_s=float(t0),
            t_end_s=float(t1),
            direction=self.directions[i],
        )

    def iter_frames(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def channel_samples(self) -> list[ChannelSample]:
        names = list(self.channels)
        return [
            ChannelSample(t_s=float(t), values={n: float(self.channels[n][k]) for n in names})
            for k, t in enumerate(self.channel_t_s)
        ]

    def channel_at(self, name: str, t_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Linear interpolation of channel ``name`` at times ``t_s``."""
        if name not in self.channels:
            raise KeyError(f"session has no channel {name!r} (has: {sorted(self.channels)})")
        return np.interp(np.asarray(t_s, dtype=np.float64), self.channel_t_s, self.channels[name])

    def truth_at(self, t_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """True drift (x_nm, y_nm) at ``t_s`` by linear interpolation, shape (..., 2)."""
        if self.truth is None:
            raise SessionError("session has no truth.csv")
        t = np.asarray(t_s, dtype=np.float64)
        x = np.interp(t, self.truth[:, 0], self.truth[:, 1])
        y = np.interp(t, self.truth[:, 0], self.truth[:, 2])
        return np.stack([x, y], axis=-1)


def validate_session(s: Session) -> None:
    """Check shapes and values; raise :class:`SessionError` naming the item."""
    if s.frames.ndim != 3:
        raise SessionError(f"frames.npy: expected (N, rows, cols), got shape {s.frames.shape}")
    if s.frames.dtype.kind != "f" or s.frames.dtype.itemsize not in (4, 8):  # either byte order
        raise SessionError(f"frames.npy: dtype must be float32 or float64, got {s.frames.dtype}")
    n = s.frames.shape[0]
    if s.frame_times.shape != (n, 2):
        raise SessionError(
            f"frames.csv: {s.frame_times.shape[0]} rows for {n} frames in frames.npy"
        )
    if len(s.directions) != n:
        raise SessionError(f"frames.csv: {len(s.directions)} directions for {n} frames")
    if not np.all(np.isfinite(s.frame_times)):
        raise SessionError("frames.csv: non-finite t_start_s or t_end_s")
    bad = np.nonzero(s.frame_times[:, 1] <= s.frame_times[:, 0])[0]
    if bad.size:
        raise SessionError(f"frames.csv: frame {int(bad[0])} has t_end_s <= t_start_s")
    px, py = s.meta.pixel_size_nm
    if not (math.isfinite(px) and math.isfinite(py) and px > 0 and py > 0):
        raise SessionError(f"session.json: pixel_size_nm must be positive, got {[px, py]}")
    if not (math.isfinite(s.meta.line_time_s) and s.meta.line_time_s > 0):
        raise SessionError(f"session.json: line_time_s must be positive, got {s.meta.line_time_s}")
    for name, col in s.channels.items():
        if col.shape != s.channel_t_s.shape:
            raise SessionError(f"channels.csv: column {name!r} length differs from t_s")
    if s.truth is not None and (s.truth.ndim != 2 or s.truth.shape[1] != 3):
        raise SessionError(f"truth.csv: expected columns t_s,x_nm,y_nm, got {s.truth.shape}")


def read_session(path: str | Path, *, mmap: bool = True) -> Session:
    """Read a session directory (format v1).

    Parameters
    ----------
    path : path-like
        The session directory.
    mmap : bool
        Memory-map ``frames.npy`` read-only instead of loading it.

    Raises
    ------
    SessionError
        A required file is missing or malformed; the message names the file and,
        for CSV files, the line.
    """
    root = Path(path)
    if not root.is_dir():
        raise SessionError(f"{root}: not a session directory")
    meta = _read_meta(root / "session.json")
    frames_path = root / "frames.npy"
    if not frames_path.is_file():
        raise SessionError(f"{frames_path}: missing")
    try:
        frames = np.load(frames_path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise SessionError(f"{frames_path}: not a readable .npy array ({err})") from None
    times, given = read_frame_windows(root / "frames.csv", directions=True)
    directions = [d or ScanDirection.UP for d in given]
    channel_t, channels = _read_channels(root / "channels.csv")
    events = _read_events(root / "events.csv")
    truth = _read_truth(root / "truth.csv")
    return Session(
        meta=meta,
        frames=frames,
        frame_times=times,
        directions=directions,
        channel_t_s=channel_t,
        channels=channels,
        events=events,
        truth=truth,
    )


def write_session(session: Session, path: str | Path) -> Path:
    """Write ``session`` as a format-v1 directory at ``path`` (created if needed).

    Files are written to temporary names and renamed, so a reader never sees a
    half-written file. Optional files of an earlier session in the same
    directory that this session does not have (channels, events, truth, the
    simulator's truth components and scenario) are removed, so a session
    written over another never carries the other's data.
    """
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    for name in _OPTIONAL_FILES:
        (root / name).unlink(missing_ok=True)
    _atomic_text(root / "session.json", json.dumps(session.meta.to_json(), indent=2) + "\n")
    tmp = root / "frames.npy.tmp"
    with tmp.open("wb") as fh:
        np.save(fh, np.ascontiguousarray(session.frames), allow_pickle=False)
    tmp.replace(root / "frames.npy")
    frame_rows = [
        [str(i), _fmt(t0), _fmt(t1), d.value]
        for i, ((t0, t1), d) in enumerate(zip(session.frame_times, session.directions, strict=True))
    ]
    _write_csv(root / "frames.csv", ["frame", "t_start_s", "t_end_s", "direction"], frame_rows)
    if session.channels:
        names = list(session.channels)
        ch_rows = [
            [_fmt(t)] + [_fmt(session.channels[n][k]) for n in names]
            for k, t in enumerate(session.channel_t_s)
        ]
        _write_csv(root / "channels.csv", ["t_s", *names], ch_rows)
    if session.events:
        ev_rows = [[_fmt(e.t_s), str(e.kind), _fmt(e.x_nm), _fmt(e.y_nm)] for e in session.events]
        _write_csv(root / "events.csv", ["t_s", "kind", "x_nm", "y_nm"], ev_rows)
    if session.truth is not None:
        tr_rows = [[_fmt(t), _fmt(x), _fmt(y)] for t, x, y in session.truth]
        _write_csv(root / "truth.csv", ["t_s", "x_nm", "y_nm"], tr_rows)
    return root


# --------------------------------------------------------------------------- helpers


def _fmt(v: float) -> str:
    return repr(float(v))


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def _write_csv(path: Path, header: list[str], rows: list[list[str]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    tmp.replace(path)


def _read_meta(path: Path) -> SessionMeta:
    if not path.is_file():
        raise SessionError(f"{path}: missing")
    try:
        doc = loads_json(
            read_text(path, max_bytes=MAX_META_BYTES, what="session.json"), what="session.json"
        )
    except ValueError as err:
        raise SessionError(f"{path}: {err}") from None
    if not isinstance(doc, dict):
        raise SessionError(f"{path}: expected a JSON object")
    if doc.get("format") != FORMAT_NAME:
        raise SessionError(f"{path}: 'format' must be {FORMAT_NAME!r}, got {doc.get('format')!r}")
    if doc.get("version") != FORMAT_VERSION:
        raise SessionError(
            f"{path}: unsupported version {doc.get('version')!r} "
            f"(this reader knows {FORMAT_VERSION})"
        )
    for key in ("pixel_size_nm", "line_time_s"):
        if key not in doc:
            raise SessionError(f"{path}: missing key {key!r}")
    ps = doc["pixel_size_nm"]
    if isinstance(ps, int | float):
        ps = [ps, ps]
    if not (
        isinstance(ps, list)
        and len(ps) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in ps)
        and all(0 < v <= MAX_PIXEL_NM for v in ps)
    ):
        raise SessionError(
            f"{path}: pixel_size_nm must be [px, py] in nm, each > 0 and <= {MAX_PIXEL_NM:g}, "
            f"got {ps!r}"
        )
    lt = doc["line_time_s"]
    if not (isinstance(lt, int | float) and not isinstance(lt, bool) and 0 <= lt <= 3600):
        raise SessionError(f"{path}: line_time_s must be a number of s in [0, 3600], got {lt!r}")
    if doc.get("fast_axis", "x") != "x":
        raise SessionError(
            f"{path}: fast_axis {doc.get('fast_axis')!r} is not supported (only 'x')"
        )
    if doc.get("units", "nm") != "nm":
        raise SessionError(f"{path}: units {doc.get('units')!r} are not supported (only 'nm')")
    start = str(doc.get("start_time", ""))
    if start:
        try:
            datetime.fromisoformat(start)
        except ValueError:
            raise SessionError(f"{path}: start_time {start!r} is not ISO-8601") from None
    known = {
        "format",
        "version",
        "pixel_size_nm",
        "line_time_s",
        "fast_axis",
        "units",
        "start_time",
        "source",
    }
    return SessionMeta(
        pixel_size_nm=(float(ps[0]), float(ps[1])),
        line_time_s=float(doc["line_time_s"]),
        start_time=start,
        source=str(doc.get("source", "")),
        extra={k: v for k, v in doc.items() if k not in known},
    )


def _read_csv(path: Path, required: list[str]) -> list[tuple[int, dict[str, str]]]:
    if not path.is_file():
        raise SessionError(f"{path}: missing")
    if path.stat().st_size > MAX_CSV_BYTES:
        raise SessionError(f"{path}: larger than {MAX_CSV_BYTES} bytes")
    # utf-8-sig: a byte-order mark (spreadsheet exports) is not part of the header.
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        try:
            return _csv_rows(path, reader, required)
        except UnicodeDecodeError as err:
            raise SessionError(
                f"{path}:{reader.line_num + 1}: not UTF-8 text (byte {err.start} of a block)"
            ) from None
        except csv.Error as err:
            raise SessionError(f"{path}:{reader.line_num}: not valid CSV ({err})") from None


def _csv_rows(
    path: Path, reader: csv.DictReader[str], required: list[str]
) -> list[tuple[int, dict[str, str]]]:
    header = [h.strip() for h in (reader.fieldnames or [])]
    missing = [c for c in required if c not in header]
    if missing:
        shown = header if len(repr(header)) < 200 else f"{repr(header)[:200]}..."
        raise SessionError(f"{path}: missing column(s) {', '.join(missing)} (header: {shown})")
    reader.fieldnames = header
    out: list[tuple[int, dict[str, str]]] = []
    for row in reader:
        if any(row.get(c) is None for c in required):
            raise SessionError(f"{path}:{reader.line_num}: too few fields")
        out.append((reader.line_num, row))
    return out


def _to_float(text: str, where: str, column: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        shown = text if len(text or "") <= 40 else f"{text[:40]}..."
        raise SessionError(f"{where}: {column} is not a number: {shown!r}") from None
    if not math.isfinite(v):
        raise SessionError(f"{where}: {column} is not finite: {text!r}")
    return v


def _to_int(text: str, where: str, column: str) -> int:
    try:
        return int(text)
    except (TypeError, ValueError):
        shown = text if len(text or "") <= 40 else f"{text[:40]}..."
        raise SessionError(f"{where}: {column} is not an integer: {shown!r}") from None


def read_frame_windows(
    path: Path, *, directions: bool
) -> tuple[npt.NDArray[np.float64], list[ScanDirection | None]]:
    """``frames.csv``: each frame's ``(t_start_s, t_end_s)`` and its direction
    (required with ``directions``, else ``None`` where the column is absent)."""
    required = ["frame", "t_start_s", "t_end_s"] + (["direction"] if directions else [])
    rows = _read_csv(path, required)
    times = np.zeros((len(rows), 2), dtype=np.float64)
    dirs: list[ScanDirection | None] = []
    for k, (line, row) in enumerate(rows):
        where = f"{path}:{line}"
        if _to_int(row["frame"], where, "frame") != k:
            raise SessionError(f"{where}: frame numbers must be 0, 1, 2, ... (got {row['frame']})")
        times[k] = (
            _to_float(row["t_start_s"], where, "t_start_s"),
            _to_float(row["t_end_s"], where, "t_end_s"),
        )
        dirs.append(scan_direction(row["direction"], where) if row.get("direction") else None)
    return times, dirs


def scan_direction(text: str, where: str) -> ScanDirection:
    """``up`` or ``down`` (any case) as a :class:`ScanDirection`."""
    try:
        return ScanDirection(text.strip().lower())
    except ValueError:
        raise SessionError(f"{where}: direction must be 'up' or 'down', got {text!r}") from None


def _read_channels(
    path: Path,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.float64]]]:
    if not path.is_file():
        return np.zeros(0, dtype=np.float64), {}
    rows = _read_csv(path, ["t_s"])
    names = [h for h in (rows[0][1].keys() if rows else []) if h != "t_s" and h]
    t = np.zeros(len(rows), dtype=np.float64)
    cols = {n: np.zeros(len(rows), dtype=np.float64) for n in names}
    for k, (line, row) in enumerate(rows):
        where = f"{path}:{line}"
        t[k] = _to_float(row["t_s"], where, "t_s")
        for n in names:
            cell = row.get(n)
            cols[n][k] = float("nan") if cell in (None, "") else _to_float(cell, where, n)
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise SessionError(f"{path}: t_s must not decrease")
    return t, cols


def _read_events(path: Path) -> list[Event]:
    if not path.is_file():
        return []
    events = []
    for line, row in _read_csv(path, ["t_s", "kind"]):
        where = f"{path}:{line}"
        try:
            kind = event_kind(row["kind"])
        except ValueError as err:
            raise SessionError(f"{where}: {err}") from None
        x = row.get("x_nm") or "0"
        y = row.get("y_nm") or "0"
        events.append(
            Event(
                t_s=_to_float(row["t_s"], where, "t_s"),
                kind=kind,
                x_nm=_to_float(x, where, "x_nm"),
                y_nm=_to_float(y, where, "y_nm"),
            )
        )
    return sorted(events, key=lambda e: e.t_s)


def _read_truth(path: Path) -> npt.NDArray[np.float64] | None:
    if not path.is_file():
        return None
    rows = _read_csv(path, ["t_s", "x_nm", "y_nm"])
    out = np.zeros((len(rows), 3), dtype=np.float64)
    for k, (line, row) in enumerate(rows):
        where = f"{path}:{line}"
        out[k] = (
            _to_float(row["t_s"], where, "t_s"),
            _to_float(row["x_nm"], where, "x_nm"),
            _to_float(row["y_nm"], where, "y_nm"),
        )
    return out

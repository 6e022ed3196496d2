"""Build a format-v1 session from real AFM files (``afmdrift import``).

Each file contributes its frames (a NanoScope file one, an ``.asd`` movie or an
``.npy``/``.tif``/``.nc`` stack all of theirs). Frames are ordered by the
header timestamps and timed relative to the first frame's start:

* ``t_start_s`` = frame timestamp − first timestamp; without timestamps, frames
  follow each other back to back in the order given.
* ``t_end_s`` = ``t_start_s`` + the frame's scan time from its header
  (NanoScope: lines / scan rate; ``.asd``: frame_time; ``.nc``: line_time_s ×
  rows). Without one, the frame interval is used (frames back to back) or the
  caller's ``frame_time_s``; ``source`` in ``session.json`` says which.
* ``line_time_s`` = the header's line time (NanoScope ``1 / Scan rate``),
  otherwise frame time / rows.
* ``direction`` from the header (NanoScope ``Frame direction``), else ``up``.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.io import AfmImage, PixelSize, calibrated, load_stack
from afmdrift.records import ScanDirection
from afmdrift.session._format import (
    Session,
    SessionError,
    SessionMeta,
    _read_channels,
    _read_events,
)

__all__ = [
    "NoFrameTimingError",
    "attach_logs",
    "import_files",
    "session_from_images",
    "stack_session",
]

_REL_TOL = 1e-6

log = logging.getLogger(__name__)


def import_files(
    paths: Sequence[str | Path],
    *,
    pixel_size_nm: PixelSize | None = None,
    channel: str = "Height",
    height_unit: str | None = None,
    frame_time_s: float | None = None,
    override_pixel_size: bool = False,
) -> Session:
    """Read AFM image files into one in-memory :class:`Session`.

    Parameters
    ----------
    paths : sequence of path-like
        Image files (any format :func:`afmdrift.io.load_stack` reads).
    pixel_size_nm : float or (float, float), optional
        Pixel size (x, y) in nm, for files without one; a file's own
        calibration is kept (a warning names both when they differ) unless
        ``override_pixel_size`` (:func:`afmdrift.io.calibrated`).
    channel : str
        Channel to read from every file (``"Height"``; ``TP`` in ``.asd``).
    height_unit : str, optional
        Unit of heights for files that store them without one.
    frame_time_s : float, optional
        Scan time of one frame, for files whose headers give no timing.

    Returns
    -------
    Session
        Frames (N, rows, cols) float64 in nm, sorted by time.

    Raises
    ------
    SessionError
        No files, shapes or pixel sizes differ between files, timing missing
        or inconsistent; the message names the file.
    afmdrift.io.ImageFileError
        A file cannot be read.
    """
    if not paths:
        raise SessionError("import: no input files given")
    images: list[AfmImage] = []
    given = _pixel_pair(pixel_size_nm)
    for p in paths:

        def read(px: tuple[float, float] | None, p: str | Path = p) -> list[AfmImage]:
            return load_stack(p, pixel_size_nm=px, channel=channel, height_unit=height_unit)

        stack, note = calibrated(
            read, given, override=override_pixel_size, pixel_of=lambda s: s[0].pixel_size_nm
        )
        if note is not None:
            log.warning("%s: %s", p, note)
        images.extend(stack)
    return session_from_images(images, frame_time_s=frame_time_s)


def _pixel_pair(pixel_size_nm: PixelSize | None) -> tuple[float, float] | None:
    """A pixel size given as one number (square pixels) or a pair, as a pair."""
    if pixel_size_nm is None:
        return None
    if isinstance(pixel_size_nm, int | float):
        return (float(pixel_size_nm), float(pixel_size_nm))
    px, py = pixel_size_nm
    return (float(px), float(py))


def session_from_images(
    images: Sequence[AfmImage], *, frame_time_s: float | None = None
) -> Session:
    """The in-memory :class:`Session` of images already read, timed as
    :func:`import_files` times them (it calls this); ``afmdrift measure`` on a
    stack uses it too.

    When the images are, in order, the frames of one float64 stack (as a
    stack file's reader gives them), the session's ``frames`` is that stack:
    it shares memory with the images' heights. Otherwise it is a copy."""
    images = list(images)
    if not images:
        raise SessionError("import: no images")
    if frame_time_s is not None and not (math.isfinite(frame_time_s) and frame_time_s > 0):
        raise SessionError(f"import: frame_time_s must be positive, got {frame_time_s}")
    _check_consistent(images)
    notes: list[str] = []
    timed = [im.timestamp is not None for im in images]
    if any(timed) and not all(timed):
        missing = images[timed.index(False)]
        raise SessionError(
            f"{missing.source}: no timestamp in its header, but other files have one; "
            "import files with and without timestamps separately"
        )
    scan_times = _scan_times(images, frame_time_s, notes)
    if all(timed):
        stamps = [im.timestamp for im in images if im.timestamp is not None]
        order = sorted(range(len(images)), key=stamps.__getitem__)
        images = [images[i] for i in order]
        scan_times = [scan_times[i] for i in order]
        starts = [(stamps[i] - stamps[order[0]]).total_seconds() for i in order]
        notes.append("frame start times from header timestamps")
    else:
        starts = list(np.cumsum([0.0, *scan_times[:-1]]))
        notes.append("no timestamps: frames taken back to back in the order given")
    times = np.array([[s, s + d] for s, d in zip(starts, scan_times, strict=True)])
    rows = images[0].shape[0]
    line_times = [im.line_time_s for im in images if im.line_time_s is not None]
    if line_times:
        line_time = float(np.median(line_times))
        notes.append("line_time_s from the file headers")
    else:
        line_time = float(np.median(scan_times)) / rows
        notes.append("line_time_s = frame time / rows")
    directions = [im.scan_direction or ScanDirection.UP for im in images]
    if any(im.scan_direction is None for im in images):
        notes.append("scan direction not in header: 'up' assumed")
    first = images[0].timestamp
    meta = SessionMeta(
        pixel_size_nm=images[0].pixel_size_nm,
        line_time_s=line_time,
        start_time=first.isoformat() if isinstance(first, datetime) else "",
        source="imported from "
        + ", ".join(dict.fromkeys(str(im.path) for im in images))
        + "; "
        + "; ".join(notes),
        extra={
            "channel": images[0].channel,
            "frame_sources": [im.source for im in images],
        },
    )
    return Session(
        meta=meta,
        frames=_frames_array(images),
        frame_times=times,
        directions=directions,
    )


def _frames_array(images: list[AfmImage]) -> npt.NDArray[np.floating]:
    """The (N, rows, cols) heights of ``images``, in order: the array they are
    views of when they are its consecutive frames (a stack file's reader gives
    them so, float64; a memory-mapped ``.npy`` stack, float32 or float64), else
    a float64 copy. A long stack is then held once, and not copied again (the
    copy cost ~5 ms per 512² frame, mostly in page faults)."""
    base = images[0].heights_nm.base
    if (
        isinstance(base, np.ndarray)
        and base.dtype in (np.dtype(np.float32), np.dtype(np.float64))
        and base.ndim == 3
        and base.shape[0] == len(images)
        and base.flags.c_contiguous
        and all(
            im.heights_nm.dtype == base.dtype
            and im.heights_nm.shape == base.shape[1:]
            and im.heights_nm.strides == base.strides[1:]
            and im.heights_nm.ctypes.data == base[i].ctypes.data
            for i, im in enumerate(images)
        )
    ):
        return base
    return np.stack([im.heights_nm for im in images], dtype=np.float64)


def _check_consistent(images: list[AfmImage]) -> None:
    ref = images[0]
    for im in images[1:]:
        if im.shape != ref.shape:
            raise SessionError(
                f"{im.source}: image is {im.shape[0]}x{im.shape[1]} px but "
                f"{ref.source} is {ref.shape[0]}x{ref.shape[1]} px; a session needs one shape"
            )
        if not all(
            math.isclose(a, b, rel_tol=_REL_TOL)
            for a, b in zip(im.pixel_size_nm, ref.pixel_size_nm, strict=True)
        ):
            raise SessionError(
                f"{im.source}: pixel size {im.pixel_size_nm} nm differs from "
                f"{ref.pixel_size_nm} nm of {ref.source}"
            )


def _scan_times(
    images: list[AfmImage], frame_time_s: float | None, notes: list[str]
) -> list[float]:
    """Scan time of each frame: header, else frame interval, else ``frame_time_s``."""
    if all(im.frame_time_s is not None for im in images):
        notes.append("frame scan times from the file headers")
        return [float(im.frame_time_s or 0.0) for im in images]
    if frame_time_s is not None:
        notes.append(f"frame scan time {frame_time_s} s given on import")
        return [im.frame_time_s or frame_time_s for im in images]
    stamps = sorted(im.timestamp for im in images if im.timestamp is not None)
    gaps = [(b - a).total_seconds() for a, b in itertools.pairwise(stamps)]
    positive = [g for g in gaps if g > 0]
    if len(stamps) == len(images) and positive:
        interval = float(np.median(positive))
        notes.append(f"frame scan time = median frame interval {interval:g} s (back to back)")
        return [im.frame_time_s or interval for im in images]
    untimed = next(im for im in images if im.frame_time_s is None)
    raise NoFrameTimingError(
        f"{untimed.source}: the file gives no frame timing; give the frame scan time "
        "(frame_time_s=..., --frame-time-s)"
    )


class NoFrameTimingError(SessionError):
    """Images whose files give no frame timing, and none was given."""


#: Frame scan time taken for a stack whose files give no timing at all, s
#: (positions do not depend on it; trajectory times do).
UNTIMED_FRAME_S = 1.0


def stack_session(images: Sequence[AfmImage]) -> tuple[Session, bool]:
    """The session of a stack or movie (or a series of single images) as
    ``afmdrift measure STACK`` and ``batch`` track it: timed as
    :func:`session_from_images` times it, or, when the files give no timing
    at all, frames :data:`UNTIMED_FRAME_S` apart, back to back. Returns the
    session and whether its frame times are the instrument's (every image
    has a timestamp)."""
    timed = all(im.timestamp is not None for im in images)
    try:
        return session_from_images(images), timed
    except NoFrameTimingError:
        return session_from_images(images, frame_time_s=UNTIMED_FRAME_S), timed


def attach_logs(
    session: Session,
    *,
    channels_csv: str | Path | None = None,
    events_csv: str | Path | None = None,
) -> Session:
    """``session`` with a lab's own channel and event logs attached.

    The files have the columns of the session format's ``channels.csv``
    (``t_s`` and one column per channel) and ``events.csv`` (``t_s, kind,
    x_nm, y_nm``; any lower-case kind is kept, ``docs/session-format.md``),
    with ``t_s`` on the session clock (0 = start of the first frame).

    Raises
    ------
    SessionError
        A file that does not exist or does not parse; the message names it
        (and the line).
    """
    channel_t_s, channels = session.channel_t_s, session.channels
    events = list(session.events)
    if channels_csv is not None:
        path = Path(channels_csv)
        if not path.is_file():
            raise SessionError(f"{path}: channel log not found")
        channel_t_s, channels = _read_channels(path)
    if events_csv is not None:
        path = Path(events_csv)
        if not path.is_file():
            raise SessionError(f"{path}: event log not found")
        events = _read_events(path)
    return Session(
        meta=session.meta,
        frames=session.frames,
        frame_times=session.frame_times,
        directions=session.directions,
        channel_t_s=channel_t_s,
        channels=channels,
        events=events,
        truth=session.truth,
    )

"""An AFM whose own software saves each finished image into a folder (``folder:PATH``).

:class:`FolderInstrument` watches a directory by polling and hands every new,
complete image file to the service as a frame, read by the same readers as
``afmdrift measure`` (:func:`afmdrift.io.load_stack`). It cannot move the scan
offset: the published d(t) is for the user's own controller.

Completeness
------------
A file becomes a frame when

1. its name is not a temporary one (dotfiles, ``~`` backups, ``.tmp``,
   ``.part``, ``.crdownload``, ``.partial``, ``.download``, ``.swp``) and its
   suffix is one :func:`~afmdrift.io.load_image` reads;
2. its size and modification time (ns) are the same in two directory scans at
   least ``poll_s`` apart, and it is not empty;
3. the reader accepts it. Every reader checks that the file holds all the data
   its header declares, so a writer that pauses longer than ``poll_s`` in the
   middle of a file gives a read error, not a partial frame. A stable file that
   does not read is logged and retried on the next scans, at most
   ``read_attempts`` times, then skipped (logged as a warning) until it changes.

The latency from the last byte written to the frame being handed out is
between one and two scan periods plus the read: 0.2–0.4 s with the default
``poll_s = 0.2``, plus the service's ``frame_poll_interval_s``. Polling was
chosen over an event library (inotify/watchdog) because it behaves the same on
network shares and every OS, its latency is bounded by a setting, and the
size-stability check needs periodic scans anyway.

Files present when the instrument first connects are not read (unless
``include_existing``): the run starts with the next image saved. A file that
is rewritten later (new size or mtime) is read again as a new frame, unless
its image data are those it gave last time (a writer that appends bytes after
an image a reader had already accepted whole): that frame would read as no
drift between the two reads.

Timing
------
The instrument clock is Unix time minus ``origin_s`` (the Unix time when the
instrument was made, whole seconds), so header dates, file mtimes and the
sensor log share one axis. For each image:

* the scan duration is ``frame_time_s``, else ``line_time_s × rows`` from the
  header, else ``line_time_s`` (``folder_line_time_s``) × rows, else a nominal
  1 ms per line (logged once: give ``folder_line_time_s``);
* the scan start is the header's date when the frame it gives ends no later
  than 60 s after the file's mtime and no more than ``max_header_age_s``
  before it (a file copied from an old run, or a wrong clock, fails this);
  otherwise the frame ends at the file's mtime (the last frame of a movie;
  earlier ones one duration apart);
* frames never overlap: a frame that starts before the previous one ended
  (header dates have 1 s resolution; files copied faster than they could be
  scanned) is moved later by the overlap, logged at debug level up to 2 s and
  as a warning beyond.

Frames of one scan are handed out in order of (end time, file name, frame in
file), one per :meth:`latest_frame` call, so none is replaced before the
service has read it. :meth:`now_s` never runs behind the last frame handed out.

Sensor log
----------
An optional CSV file in the folder (``sensors.csv`` by default) gives the
channels. Its first line names the columns: a time column, ``time``
(ISO-8601; without a UTC offset it is local time) or ``unix_s`` (seconds since
1970-01-01 UTC), and one column per channel with numbers (``temperature_c``,
``humidity_pct``, ...). Lines starting with ``#`` and rows that do not parse
are skipped. The file is read incrementally as lines are appended; a file
that shrinks is read again from the start. :meth:`read_channels` returns the
last complete row.
"""

from __future__ import annotations

import asyncio
import csv
import hashlib
import io
import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from types import MappingProxyType

from afmdrift._version import __version__
from afmdrift.drivers._base import ConnectOnEnter
from afmdrift.drivers._protocol import InstrumentDisconnected, InstrumentError
from afmdrift.io import SUFFIXES, AfmImage, ImageFileError, load_stack
from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo, ScanDirection

__all__ = ["FolderInstrument", "OffsetNotSupportedError", "is_temporary_name"]

log = logging.getLogger(__name__)

_TEMP_SUFFIXES = (
    ".tmp",
    ".temp",
    ".part",
    ".partial",
    ".crdownload",
    ".download",
    ".swp",
    ".lock",
    ".bak",
)
#: A header date may put the frame's end this far after the file's mtime.
_CLOCK_SKEW_S = 60.0
#: Overlaps up to this are the header's 1 s resolution, not a wrong clock.
_QUIET_SHIFT_S = 2.0
#: Line time used when neither the header nor the configuration gives one.
_NOMINAL_LINE_TIME_S = 1e-3
#: Largest sensor-log chunk read per call.
_MAX_SENSOR_READ = 1 << 20


class OffsetNotSupportedError(InstrumentError):
    """The instrument cannot move its scan offset (a folder of saved images).

    An :class:`~afmdrift.drivers.InstrumentError` with the SCPI code −221,
    "Settings conflict".
    """

    def __init__(self, message: str) -> None:
        super().__init__(-221, message, command="set_offset")


def is_temporary_name(name: str) -> bool:
    """A name that vendor software, editors or copy tools use while writing."""
    lower = name.lower()
    return (
        lower.startswith((".", "~"))
        or lower.endswith("~")
        or lower.endswith(_TEMP_SUFFIXES)
        or lower.startswith("~$")
    )


def _is_image_name(name: str) -> bool:
    if is_temporary_name(name):
        return False
    suffix = Path(name).suffix.lower()
    return suffix in SUFFIXES or (len(suffix) == 4 and suffix[1:].isdigit())


@dataclass(slots=True)
class _Watched:
    """What the scans know of one file."""

    signature: tuple[int, int]  # (size, mtime_ns)
    mtime_s: float
    state: str  # "pending", "read", "failed", "ignored"
    attempts: int = 0


def _digest(images: list[AfmImage]) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for image in images:
        h.update(image.heights_nm.tobytes())
    return h.digest()


class FolderInstrument(ConnectOnEnter):
    """A folder of image files saved by vendor software, seen as an instrument.

    Parameters
    ----------
    path : path-like
        The folder the AFM software saves its images into.
    poll_s : float
        Least time between two directory scans.
    line_time_s : float, optional
        Time per scan line for files whose header gives none.
    channel : str
        Channel read from each file (``"Height"``: the topography of any format).
    max_header_age_s : float
        Header dates that end earlier than this before the file's mtime are not
        trusted (see the module docstring).
    sensor_file : str
        Name of the sensor log inside the folder.
    include_existing : bool
        Read the files already in the folder at the first connect too.
    read_attempts : int
        Reads of a stable file that fail before it is skipped until it changes.
    clock : callable
        Unix time in s (default :func:`time.time`); tests pass their own.
    origin_s : float, optional
        Unix time of instrument time 0 (default: ``clock()`` at construction,
        whole seconds).

    Attributes
    ----------
    delivered : list of str
        ``name`` or ``name:i`` of every frame handed out, in order.
    skipped : list of (str, str)
        Files given up after ``read_attempts`` failed reads, with the error.
    read_errors : int
        Failed reads (retried or not).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        poll_s: float = 0.2,
        line_time_s: float | None = None,
        channel: str = "Height",
        max_header_age_s: float = 3600.0,
        sensor_file: str = "sensors.csv",
        include_existing: bool = False,
        read_attempts: int = 3,
        clock: Callable[[], float] = time.time,
        origin_s: float | None = None,
    ) -> None:
        if not (math.isfinite(poll_s) and poll_s > 0):
            raise ValueError(f"poll_s must be > 0, got {poll_s!r}")
        if line_time_s is not None and not (math.isfinite(line_time_s) and line_time_s > 0):
            raise ValueError(f"line_time_s must be > 0, got {line_time_s!r}")
        if read_attempts < 1:
            raise ValueError(f"read_attempts must be >= 1, got {read_attempts}")
        self.path = Path(path)
        self.poll_s = float(poll_s)
        self.line_time_s = line_time_s
        self.channel = channel
        self.max_header_age_s = float(max_header_age_s)
        self.include_existing = include_existing
        self.read_attempts = read_attempts
        self._clock = clock
        self.origin_s = float(math.floor(clock())) if origin_s is None else float(origin_s)
        self.delivered: list[str] = []
        self.skipped: list[tuple[str, str]] = []
        self.read_errors = 0
        self._files: dict[str, _Watched] = {}
        # digest of the image data each file last gave, to tell a rewrite that
        # changed nothing in it (e.g. trailing bytes after a complete image)
        self._digests: dict[str, bytes] = {}
        self._queue: deque[tuple[str, Frame]] = deque()
        self._latest: Frame | None = None
        self._next_index = 0
        self._last_end_s = -math.inf
        self._now_floor_s = -math.inf
        self._last_scan_s = -math.inf
        self._started = False
        self._warned_no_line_time = False
        self._scan_lock = asyncio.Lock()
        self._sensors = _SensorLog(self.path / sensor_file, self._to_instrument_s)

    def _to_instrument_s(self, unix_s: float) -> float:
        return unix_s - self.origin_s

    # ---------------------------------------------------------------- lifecycle

    async def connect(self) -> None:
        """Check the folder; at the first connect, note the files already there."""
        if not self.path.is_dir():
            raise InstrumentDisconnected(f"folder:{self.path}: no such directory")
        if not self._started:
            async with self._scan_lock:
                await asyncio.to_thread(self._scan, initial=True)
            self._started = True

    async def close(self) -> None:
        return None

    async def identify(self) -> InstrumentInfo:
        return InstrumentInfo(
            vendor="afmdrift", model="FolderInstrument", serial=str(self.path), firmware=__version__
        )

    # ---------------------------------------------------------------- Instrument

    async def now_s(self) -> float:
        """Unix time on the instrument axis, never behind the last frame handed out."""
        self._now_floor_s = max(self._now_floor_s, self._to_instrument_s(self._clock()))
        return self._now_floor_s

    async def latest_frame(self) -> Frame | None:
        """The next complete frame not yet handed out, else the last one handed out.

        Scans the folder when ``poll_s`` has passed since the last scan and no
        frame is waiting.
        """
        if not self._queue and self._clock() - self._last_scan_s >= self.poll_s:
            async with self._scan_lock:
                ready = await asyncio.to_thread(self._scan, initial=False)
                if ready:
                    await asyncio.to_thread(self._read_ready, ready)
        if self._queue:
            name, frame = self._queue.popleft()
            self._latest = frame
            self.delivered.append(name)
            self._now_floor_s = max(self._now_floor_s, frame.t_end_s)
        return self._latest

    async def read_channels(self) -> ChannelSample:
        """The last complete row of the sensor log (none: no values, at now)."""
        sample = await asyncio.to_thread(self._sensors.latest)
        return sample if sample is not None else ChannelSample(t_s=await self.now_s())

    async def events(self, start: int = 0) -> list[Event]:
        """A folder has no event log: always empty."""
        if start < 0:
            raise ValueError(f"events: start must be >= 0, got {start}")
        return []

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        """Refused: vendor software saving files cannot be told to move."""
        raise OffsetNotSupportedError(
            f"folder:{self.path}: a folder instrument cannot move the scan offset; "
            "apply the published d(t) with your own controller ([service] closed_loop = false)"
        )

    async def get_offset(self) -> tuple[float, float]:
        return (0.0, 0.0)

    # ---------------------------------------------------------------- scanning

    def _scan(self, *, initial: bool) -> list[str]:
        """One directory scan: the names whose signature held since the last one."""
        self._last_scan_s = self._clock()
        seen: dict[str, tuple[tuple[int, int], float]] = {}
        try:
            with os.scandir(self.path) as entries:
                for entry in entries:
                    if not _is_image_name(entry.name):
                        continue
                    try:
                        if not entry.is_file():
                            continue
                        st = entry.stat()
                    except OSError:  # removed while scanning
                        continue
                    seen[entry.name] = ((st.st_size, st.st_mtime_ns), st.st_mtime)
        except OSError as err:
            raise InstrumentDisconnected(f"folder:{self.path}: cannot list: {err}") from None
        ready: list[str] = []
        for name, (signature, mtime_s) in seen.items():
            known = self._files.get(name)
            if known is None:
                state = "ignored" if initial and not self.include_existing else "pending"
                self._files[name] = _Watched(signature, mtime_s, state)
            elif known.signature != signature:
                if known.state in ("read", "failed", "ignored"):
                    log.debug("%s changed; watching it again", name)
                self._files[name] = _Watched(signature, mtime_s, "pending")
            elif known.state == "pending" and signature[0] > 0:
                ready.append(name)
        for name in set(self._files) - set(seen):
            del self._files[name]
            self._digests.pop(name, None)
        return ready

    def _read_ready(self, names: list[str]) -> None:
        """Read the stable files; queue their frames in time order."""
        new: list[tuple[float, str, int, float, AfmImage]] = []
        for name in names:
            watched = self._files[name]
            try:
                images = load_stack(self.path / name, channel=self.channel)
            except ImageFileError as err:
                self.read_errors += 1
                watched.attempts += 1
                if watched.attempts >= self.read_attempts:
                    watched.state = "failed"
                    self.skipped.append((name, str(err)))
                    log.warning(
                        "%s: skipped after %d failed reads (it is read again if it changes): %s",
                        name,
                        watched.attempts,
                        err,
                    )
                else:
                    log.info("%s: not readable yet (%s); retrying", name, err)
                continue
            watched.state = "read"
            digest = _digest(images)
            if self._digests.get(name) == digest:
                # A writer finished a file whose image data a reader had
                # already accepted whole: the same frame again would read as
                # no drift over the time between the two reads.
                log.debug("%s changed, but not its image data; not read again", name)
                continue
            self._digests[name] = digest
            for k, (t_start, t_end, image) in enumerate(self._times(images, watched.mtime_s)):
                new.append((t_end, name, k, t_start, image))
        new.sort(key=lambda item: item[:3])
        for t_end, name, _, t_start, image in new:
            label = name if image.frame is None else f"{name}:{image.frame}"
            self._queue.append((label, self._frame(image, t_start, t_end, label)))

    def _times(self, images: list[AfmImage], mtime_s: float) -> list[tuple[float, float, AfmImage]]:
        """(start, end, image) per image of one file, before overlaps are resolved."""
        out = []
        n = len(images)
        end_by_mtime = self._to_instrument_s(mtime_s)
        for i, image in enumerate(images):
            duration = self._duration(image)
            start: float | None = None
            if image.timestamp is not None:
                t0 = self._to_instrument_s(image.timestamp.timestamp())
                if (
                    end_by_mtime - self.max_header_age_s
                    <= t0 + duration
                    <= end_by_mtime + (_CLOCK_SKEW_S)
                ):
                    start = t0
                elif i == 0:
                    log.info(
                        "%s: header date %s does not fit the file's mtime; timed by its mtime",
                        image.path.name,
                        image.timestamp.isoformat(),
                    )
            if start is None:
                start = end_by_mtime - (n - i) * duration
            out.append((start, start + duration, image))
        return out

    def _duration(self, image: AfmImage) -> float:
        rows = image.shape[0]
        if image.frame_time_s is not None and image.frame_time_s > 0:
            return image.frame_time_s
        if image.line_time_s is not None and image.line_time_s > 0:
            return image.line_time_s * rows
        if self.line_time_s is not None:
            return self.line_time_s * rows
        if not self._warned_no_line_time:
            log.warning(
                "%s: no line time in the header and no folder_line_time_s; "
                "using a nominal %.0f ms per line",
                image.path.name,
                _NOMINAL_LINE_TIME_S * 1e3,
            )
            self._warned_no_line_time = True
        return _NOMINAL_LINE_TIME_S * rows

    def _frame(self, image: AfmImage, t_start: float, t_end: float, label: str) -> Frame:
        overlap = self._last_end_s - t_start
        if overlap > 0:
            (log.debug if overlap <= _QUIET_SHIFT_S else log.warning)(
                "%s: starts %.3f s before the previous frame ended; moved later by that much",
                label,
                overlap,
            )
            t_start, t_end = t_start + overlap, t_end + overlap
        self._last_end_s = t_end
        frame = Frame(
            index=self._next_index,
            heights_nm=image.heights_nm,
            pixel_size_nm=image.pixel_size_nm,
            t_start_s=t_start,
            t_end_s=t_end,
            direction=image.scan_direction or ScanDirection.UP,
        )
        self._next_index += 1
        return frame


class _SensorLog:
    """The folder's sensor CSV, read incrementally (format in the module docstring)."""

    def __init__(self, path: Path, to_instrument_s: Callable[[float], float]) -> None:
        self.path = path
        self._to_instrument_s = to_instrument_s
        self._offset = 0
        self._columns: list[str] | None = None
        self._latest: ChannelSample | None = None
        self.bad_rows = 0

    def latest(self) -> ChannelSample | None:
        try:
            size = self.path.stat().st_size
        except OSError:
            return self._latest
        if size < self._offset:  # rewritten: start again
            self._offset, self._columns, self._latest = 0, None, None
        if size == self._offset:
            return self._latest
        try:
            with self.path.open("rb") as f:
                f.seek(self._offset)
                chunk = f.read(min(size - self._offset, _MAX_SENSOR_READ))
        except OSError:
            return self._latest
        complete = chunk[: chunk.rfind(b"\n") + 1]  # only whole lines
        self._offset += len(complete)
        text = complete.decode("utf-8", errors="replace")
        for row in csv.reader(io.StringIO(text)):
            self._row([c.strip() for c in row])
        return self._latest

    def _row(self, row: list[str]) -> None:
        if not row or not row[0] or row[0].startswith("#"):
            return
        if self._columns is None:
            if row[0] not in ("time", "unix_s"):
                log.warning(
                    "%s: first column is %r; expected 'time' or 'unix_s'", self.path, row[0]
                )
                self.bad_rows += 1
                return
            self._columns = row
            return
        try:
            if len(row) != len(self._columns):
                raise ValueError(f"{len(row)} fields for {len(self._columns)} columns")
            unix_s = (
                float(row[0])
                if self._columns[0] == "unix_s"
                else datetime.fromisoformat(row[0]).timestamp()
            )
            values = {name: float(v) for name, v in zip(self._columns[1:], row[1:], strict=True)}
            if not all(math.isfinite(v) for v in (unix_s, *values.values())):
                raise ValueError("non-finite value")
        except ValueError as err:
            self.bad_rows += 1
            log.debug("%s: row %r skipped: %s", self.path, row, err)
            return
        self._latest = ChannelSample(
            t_s=self._to_instrument_s(unix_s), values=MappingProxyType(values)
        )

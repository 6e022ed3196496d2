"""Nanonis ``.sxm`` scan files: a small reader and writer of our own.

No well-kept library reads ``.sxm`` safely: pySPM's ``SXM`` loops for ever on
a file whose header has no end tag (a partial file, which the folder
instrument meets routinely), and nanonispy is unmaintained. The layout is
simple and documented, so afmdrift reads it here, with limits.

Format (Nanonis file format v1 as described by SPECS, reproduced in the gxsm
plugin request "File PlugIn for Nanonis File Format",
https://sourceforge.net/p/gxsm/plugin-requests/3/; the data layout as pySPM's
``SXM.get_channel`` reads it):

* An ASCII header of tags ``:NAME:`` on their own line, each followed by
  value lines, ending with ``:SCANIT_END:``; then the bytes ``\\x1a\\x04`` and
  the binary data.
* ``:SCANIT_TYPE:`` ``FLOAT MSBFIRST`` (big-endian float32; ``LSBFIRST``,
  ``INT``, ``UINT`` and ``DOUBLE`` also occur).
* ``:SCAN_PIXELS:`` pixels per line (x) and lines (y); ``:SCAN_RANGE:`` the
  scanned width and height in m; ``:SCAN_DIR:`` ``up`` or ``down``.
* ``:DATA_INFO:`` a tab-separated table (``Channel Name Unit Direction
  Calibration Offset``), one row per channel; ``Direction`` ``both`` stores a
  forward and a backward image, in that order. The images follow one another
  in table order, each ``lines × pixels`` values, lines in the order scanned.
* ``:REC_DATE:`` ``dd.mm.yyyy`` and ``:REC_TIME:`` ``hh:mm:ss``: "the date and
  time at which the image was taken", read here as the start of the scan
  (SPECS does not say start or end; a 1 s resolution).
  ``:SCAN_TIME:`` the forward and backward time per line in s;
  ``:ACQ_TIME:`` the time the whole image took, in s.

Only the forward image is read. Lines are stored in scan order, so a ``down``
scan starts at the top of the frame: its rows are reversed here, so that row 0
is the bottom line of the frame for both directions, and ``scan_direction``
says in which order the rows were scanned (``up``: 0 → N−1). The channel
``Height`` (or ``Topography``) selects ``Z``.

A file shorter than its header declares (a partial write) is refused with
:class:`ImageFileError`, never read in part.
"""

from __future__ import annotations

import re
from datetime import datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.io._channels import pick_channel
from afmdrift.io._image import AfmImage, ImageFileError, length_unit_to_nm
from afmdrift.records import ScanDirection

__all__ = ["read_sxm", "write_sxm"]

_END_TAG = b":SCANIT_END:"
_DATA_MARK = b"\x1a\x04"
#: Longest header read (real headers are a few kB).
_MAX_HEADER_BYTES = 1 << 20
_TYPES = {"FLOAT": "f4", "INT": "i4", "UINT": "u4", "DOUBLE": "f8"}
_ALIASES = {"height": "Z", "topography": "Z"}
#: Most values one file may declare (the limit of :func:`afmdrift.io.load_image`).
_MAX_VALUES = 1 << 28


def _parse_header(text: str) -> dict[str, list[str]]:
    header: dict[str, list[str]] = {}
    key: str | None = None
    for line in text.splitlines():
        m = re.fullmatch(r":([^:]+):", line.strip())
        if m:
            key = m.group(1)
            header[key] = []
        elif key is not None and line.strip():
            header[key].append(line)
    return header


def _numbers(header: dict[str, list[str]], key: str, count: int, path: Path) -> list[float]:
    lines = header.get(key)
    if not lines:
        raise ImageFileError(f"{path}: .sxm header has no :{key}:")
    try:
        values = [float(v) for v in lines[0].split()]
    except ValueError:
        raise ImageFileError(
            f"{path}: .sxm header :{key}: {lines[0].strip()!r} is not numeric"
        ) from None
    if len(values) < count or not all(np.isfinite(values[:count])):
        raise ImageFileError(
            f"{path}: .sxm header :{key}: needs {count} finite numbers, got {lines[0].strip()!r}"
        )
    return values[:count]


def _channels(header: dict[str, list[str]], path: Path) -> list[tuple[str, str, int]]:
    """(name, unit, number of images) per channel of ``:DATA_INFO:``."""
    rows = [line.split("\t") for line in header.get("DATA_INFO", [])]
    rows = [[c.strip() for c in r if c.strip()] for r in rows]
    rows = [r for r in rows if r]
    if len(rows) < 2 or rows[0][:4] != ["Channel", "Name", "Unit", "Direction"]:
        raise ImageFileError(f"{path}: .sxm header has no readable :DATA_INFO: table")
    out = []
    for r in rows[1:]:
        if len(r) < 4 or r[3] not in ("both", "forward", "backward"):
            raise ImageFileError(f"{path}: .sxm :DATA_INFO: row {r!r} is not understood")
        out.append((r[1], r[2], 2 if r[3] == "both" else 1))
    return out


def read_sxm(path: Path, *, channel: str) -> AfmImage:
    """Read the forward image of one channel of a Nanonis ``.sxm`` file.

    Parameters
    ----------
    path : Path
        The ``.sxm`` file.
    channel : str
        A ``:DATA_INFO:`` channel name (``Z``; ``Height`` is an alias).

    Returns
    -------
    AfmImage
        Heights in nm, shape (lines, pixels); ``timestamp`` (scan start),
        ``line_time_s``, ``frame_time_s`` and ``scan_direction`` when the header
        gives them.

    Raises
    ------
    ImageFileError
        No header end (truncated), unknown data type, channel absent, a unit
        that is not a length, or fewer data bytes than the header declares.
    """
    with path.open("rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
        end = head.find(_END_TAG)
        if not head.startswith(b":"):
            raise ImageFileError(f"{path}: not a Nanonis .sxm file (no ':TAG:' header)")
        if end < 0:
            raise ImageFileError(f"{path}: truncated .sxm file (no {_END_TAG.decode()} in header)")
        mark = head.find(_DATA_MARK, end)
        if mark < 0 or mark - end > 64:
            raise ImageFileError(f"{path}: truncated .sxm file (no data mark after the header)")
        data_start = mark + len(_DATA_MARK)
        header = _parse_header(head[:end].decode("latin-1"))
        cols_f, rows_f = _numbers(header, "SCAN_PIXELS", 2, path)
        cols, rows = int(cols_f), int(rows_f)
        if cols < 1 or rows < 1 or cols * rows > _MAX_VALUES:
            raise ImageFileError(f"{path}: .sxm :SCAN_PIXELS: {cols} × {rows} is not usable")
        kind = (header.get("SCANIT_TYPE") or [""])[0].split()
        if len(kind) != 2 or kind[0] not in _TYPES or kind[1] not in ("MSBFIRST", "LSBFIRST"):
            raise ImageFileError(f"{path}: .sxm :SCANIT_TYPE: {' '.join(kind)!r} is not supported")
        dtype = np.dtype((">" if kind[1] == "MSBFIRST" else "<") + _TYPES[kind[0]])
        channels = _channels(header, path)
        names = [c[0] for c in channels]
        want = pick_channel(names, _ALIASES.get(channel.lower(), channel), where=str(path))
        k = names.index(want)
        image_bytes = rows * cols * dtype.itemsize
        total = data_start + sum(c[2] for c in channels) * image_bytes
        size = path.stat().st_size
        if size < total:
            raise ImageFileError(
                f"{path}: truncated .sxm file ({size} bytes; the header declares {total})"
            )
        f.seek(data_start + sum(c[2] for c in channels[:k]) * image_bytes)
        raw = np.frombuffer(f.read(image_bytes), dtype=dtype)
    z_factor = length_unit_to_nm(channels[k][1], where=f"{path}: channel {want!r} unit")
    image = raw.astype(np.float64).reshape(rows, cols) * z_factor
    if not np.all(np.isfinite(image)):
        raise ImageFileError(f"{path}: channel {want!r} contains non-finite heights")
    width_m, height_m = _numbers(header, "SCAN_RANGE", 2, path)
    pixel = (width_m * 1e9 / cols, height_m * 1e9 / rows)
    direction_text = (header.get("SCAN_DIR") or [""])[0].strip().lower()
    direction = {"up": ScanDirection.UP, "down": ScanDirection.DOWN}.get(direction_text)
    if direction is ScanDirection.DOWN:
        image = image[::-1]
    line_time = None
    if header.get("SCAN_TIME"):
        line_time = sum(_numbers(header, "SCAN_TIME", 2, path))
    elif header.get("ACQ_TIME"):
        line_time = _numbers(header, "ACQ_TIME", 1, path)[0] / rows
    if line_time is not None and not line_time > 0:
        line_time = None
    return AfmImage(
        heights_nm=np.ascontiguousarray(image),
        pixel_size_nm=pixel,
        path=path,
        channel=want,
        timestamp=_rec_time(header, path),
        frame_time_s=line_time * rows if line_time is not None else None,
        line_time_s=line_time,
        scan_direction=direction,
    )


def _rec_time(header: dict[str, list[str]], path: Path) -> datetime | None:
    date = (header.get("REC_DATE") or [""])[0].strip()
    clock = (header.get("REC_TIME") or [""])[0].strip()
    if not date or not clock:
        return None
    try:
        return datetime.strptime(f"{date} {clock}", "%d.%m.%Y %H:%M:%S")
    except ValueError:
        raise ImageFileError(
            f"{path}: .sxm :REC_DATE:/:REC_TIME: {date!r} {clock!r} is not dd.mm.yyyy hh:mm:ss"
        ) from None


def write_sxm(
    path: str | Path,
    heights_nm: npt.ArrayLike,
    *,
    pixel_size_nm: tuple[float, float],
    start: datetime,
    line_time_s: float,
    direction: ScanDirection = ScanDirection.UP,
) -> Path:
    """Write one ``Z`` channel (forward only) as a Nanonis ``.sxm`` file.

    For tests, demos and the folder instrument's benchmark: simulator frames
    saved as a Nanonis controller would save them. ``heights_nm`` has row 0 at
    the bottom of the frame whatever the direction (as :func:`read_sxm`
    returns it); a ``down`` frame is stored top line first. ``start`` is
    written to the second (``:REC_TIME:`` has no fraction), ``line_time_s`` as
    equal forward and backward halves of ``:SCAN_TIME:``.
    """
    image = np.asarray(heights_nm, dtype=np.float64)
    if image.ndim != 2:
        raise ValueError(f"heights_nm must be 2-D, got shape {image.shape}")
    rows, cols = image.shape
    stored = image[::-1] if direction is ScanDirection.DOWN else image
    half = line_time_s / 2
    header = "\n".join(
        [
            ":NANONIS_VERSION:",
            "2",
            ":SCANIT_TYPE:",
            "              FLOAT            MSBFIRST",
            ":REC_DATE:",
            start.strftime("%d.%m.%Y"),
            ":REC_TIME:",
            start.strftime("%H:%M:%S"),
            ":ACQ_TIME:",
            f"{line_time_s * rows:.1f}",
            ":SCAN_PIXELS:",
            f"       {cols}       {rows}",
            ":SCAN_TIME:",
            f"             {half:.6E}             {half:.6E}",
            ":SCAN_RANGE:",
            f"           {pixel_size_nm[0] * cols * 1e-9:.9E}"
            f"           {pixel_size_nm[1] * rows * 1e-9:.9E}",
            ":SCAN_DIR:",
            direction.value,
            ":DATA_INFO:",
            "\tChannel\tName\tUnit\tDirection\tCalibration\tOffset",
            "\t14\tZ\tm\tforward\t1.000E+0\t0.000E+0",
            "",
            ":SCANIT_END:",
            "",
            "",
        ]
    )
    p = Path(path)
    p.write_bytes(header.encode("latin-1") + _DATA_MARK + (stored * 1e-9).astype(">f4").tobytes())
    return p

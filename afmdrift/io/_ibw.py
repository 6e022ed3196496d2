"""Asylum Research (Oxford Instruments) ``.ibw`` images: Igor binary waves.

The wave is read with igor2 (``igor2.binarywave.load``), the maintained Igor
reader that AFMReader's ``load_ibw`` is built on. We call igor2 directly rather
than ``AFMReader.ibw.load_ibw`` because that function returns one pixel size
(slow-axis only), converts every channel to nm whatever its unit, flips the
rows for display and drops the note's timing.

Format facts used (WaveMetrics Technical Note TN003, "Igor Binary Wave
Format", for version 5 files):

* A 64-byte ``BinHeader5`` (``int16`` version = 5, checksum, then ``int32``
  sizes: ``wfmSize``, ``formulaSize``, ``noteSize``, ``dataEUnitsSize``,
  four ``dimEUnitsSize``, four ``dimLabelsSize``, ``sIndicesSize`` and two
  reserved), a 320-byte ``WaveHeader5`` (``npnts`` at byte 12, ``type`` at
  16, ``nDim[4]`` at 68, ``sfA[4]``/``sfB[4]`` at 84/116, ``dataUnits`` at
  148, ``dimUnits[4][4]`` at 152), then the data (``wfmSize`` − 320 bytes,
  column-major: dimension 0 varies fastest), the formula, the note and the
  optional units and dimension labels (32 bytes per label; the first label of
  a dimension names the dimension itself). The byte order is the writer's;
  the version field tells which.
* Asylum stores an image as a 3-D wave (points, lines, channels): dimension 0
  runs along the fast axis (x), dimension 1 along the slow axis (y), and the
  layer labels of dimension 2 name the channels (``HeightTrace``,
  ``HeightRetrace``, ``ZSensorTrace``, ``AmplitudeTrace``, ``PhaseTrace``...).
  Line 0 is the bottom of the image (Igor draws images with y upward), so rows
  are kept in stored order: row 0 is the bottom line whatever the scan
  direction.
* The wave note holds Asylum's settings as ``Key: value`` lines separated by
  carriage returns. Used here: ``FastScanSize`` and ``SlowScanSize`` (m),
  ``ScanRate`` (Hz, lines per second, trace and retrace: ``line_time_s =
  1 / ScanRate``), ``Date`` (``YYYY-MM-DD``) with ``Time`` (``h:mm:ss AM``
  or 24-hour) and, when present, ``ScanDown`` (1: the frame was scanned top
  to bottom). Without the scan sizes the wave scaling (``sfA`` in
  ``dimUnits``) gives the pixel size.

Asylum writes the file when a frame is finished, so the note's date is taken
as the end of the capture and ``timestamp`` is that date minus the frame time
(the same reading as NanoScope's ``\\Date``); the sample files behind this
reader were written from the format description, not recorded on an Asylum
instrument, so this rests on that description.

Heights: Asylum stores SI values. A channel is converted with the wave's data
unit when that is a length; otherwise height-like channels (``Height``,
``ZSensor``, ``Amplitude``, ``Deflection``) are taken as metres, and other
channels (phase in degrees, ...) are refused as not heights.
"""

from __future__ import annotations

import logging
import re
import struct
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from afmdrift.io._channels import pick_channel
from afmdrift.io._image import (
    AfmImage,
    ImageFileError,
    MissingPixelSizeError,
    length_unit_to_nm,
)
from afmdrift.records import ScanDirection

__all__ = ["read_ibw"]

_BIN_HEADER = 64
_WAVE_HEADER = 320
#: Igor number types (TN003): NT_FP32, NT_FP64, NT_I8, NT_I16, NT_I32 and the unsigned ones.
_ITEM_SIZE = {2: 4, 4: 8, 8: 1, 0x10: 2, 0x20: 4, 0x48: 1, 0x50: 2, 0x60: 4}
_METRE_CHANNELS = ("height", "zsensor", "amplitude", "deflection")
_ALIASES = {"topography": "Height"}
#: Most values one file may declare (the limit of :func:`afmdrift.io.load_image`).
_MAX_VALUES = 1 << 28


def read_ibw(
    path: Path, *, channel: str, pixel_size_nm: tuple[float, float] | None = None
) -> AfmImage:
    """Read one channel of an Asylum Research ``.ibw`` image (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.ibw`` file.
    channel : str
        A layer label such as ``"HeightTrace"`` or ``"ZSensorRetrace"``;
        ``"Height"`` (the default) selects ``HeightTrace``, and a name without
        ``Trace``/``Retrace`` selects its trace.
    pixel_size_nm : (float, float), optional
        Used when the file gives no scan size.

    Returns
    -------
    AfmImage
        Heights in nm, shape (lines, points), row 0 the bottom line;
        ``timestamp``, ``line_time_s``, ``frame_time_s`` and ``scan_direction``
        when the note gives them.

    Raises
    ------
    ImageFileError
        Not an Igor version 5 wave, fewer bytes than the headers declare, no
        image, channel absent or not a height, an implausible or missing scan
        size, or a garbled date.
    """
    _check_layout(path)
    from igor2 import binarywave

    # igor2 logs an ERROR before raising on data it cannot shape; the error
    # reaches the user as ImageFileError.
    logging.getLogger("igor2").setLevel(logging.CRITICAL)
    wave = binarywave.load(str(path))["wave"]
    data = np.asarray(wave["wData"])
    if data.ndim == 2:
        data = data[:, :, np.newaxis]
    if data.ndim != 3 or min(data.shape) == 0 or data.dtype.kind not in "iuf":
        raise ImageFileError(f"{path}: .ibw wave of shape {data.shape} is not an image")
    labels = _layer_labels(wave, data.shape[2])
    k, name = _select(labels, channel, path)
    z_factor = _height_factor(wave, name, path)
    heights = np.ascontiguousarray(data[:, :, k].T.astype(np.float64) * z_factor)
    if not np.all(np.isfinite(heights)):
        raise ImageFileError(f"{path}: channel {name!r} contains non-finite heights")
    rows, cols = heights.shape
    note = _parse_note(wave.get("note", b""))
    pixel = _pixel_size(note, wave, rows, cols, path) or pixel_size_nm
    if pixel is None:
        raise MissingPixelSizeError(
            f"{path}: .ibw file gives no scan size (note FastScanSize/SlowScanSize or wave "
            "scaling with length units); give pixel_size_nm (--pixel-size-nm)"
        )
    rate = _positive_number(note, "ScanRate", path)
    line_time = 1.0 / rate if rate else None
    frame_time = rows * line_time if line_time else None
    date = _note_date(note, path)
    timestamp = date - timedelta(seconds=frame_time) if date and frame_time else date
    down = note.get("ScanDown", "").strip()
    direction = {"1": ScanDirection.DOWN, "0": ScanDirection.UP}.get(down)
    return AfmImage(
        heights_nm=heights,
        pixel_size_nm=pixel,
        path=path,
        channel=name,
        timestamp=timestamp,
        frame_time_s=frame_time,
        line_time_s=line_time,
        scan_direction=direction,
    )


def _check_layout(path: Path) -> None:
    """Refuse anything but a complete Igor version 5 wave before igor2 parses it."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(_BIN_HEADER + _WAVE_HEADER)
    if len(head) < 2:
        raise ImageFileError(f"{path}: not an Igor binary wave (file of {size} bytes)")
    order = next((o for o in "<>" if struct.unpack(f"{o}h", head[:2])[0] == 5), None)
    if order is None:
        version = struct.unpack("<h", head[:2])[0]
        raise ImageFileError(
            f"{path}: not an Igor binary wave version 5 (version field {version}); "
            "Asylum images are version 5"
        )
    if len(head) < _BIN_HEADER + _WAVE_HEADER:
        raise ImageFileError(f"{path}: truncated .ibw file ({size} bytes; headers need 384)")
    sizes = struct.unpack(f"{order}15i", head[4:64])
    if min(sizes) < 0:
        raise ImageFileError(f"{path}: .ibw header declares a negative section size {sizes}")
    wfm_size = sizes[0]
    npnts, kind = struct.unpack(f"{order}ih", head[64 + 12 : 64 + 18])
    dims = struct.unpack(f"{order}4i", head[64 + 68 : 64 + 84])
    if kind not in _ITEM_SIZE:
        raise ImageFileError(f"{path}: .ibw number type {kind:#x} is not an image type")
    shape = [n for n in dims if n > 0]
    count = int(np.prod(shape)) if shape else 0
    if count != npnts or count == 0 or count > _MAX_VALUES:
        raise ImageFileError(
            f"{path}: .ibw header declares {npnts} points for dimensions {dims}; not usable"
        )
    if wfm_size != _WAVE_HEADER + count * _ITEM_SIZE[kind]:
        raise ImageFileError(
            f"{path}: .ibw header wfmSize {wfm_size} does not match {count} points of "
            f"{_ITEM_SIZE[kind]} bytes"
        )
    total = _BIN_HEADER + sum(sizes[:-2])
    if size < total:
        raise ImageFileError(
            f"{path}: truncated .ibw file ({size} bytes; the headers declare {total})"
        )


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.split(b"\0", 1)[0].decode("latin-1")
    if isinstance(value, np.ndarray):
        return _text(value.tobytes())
    return str(value)


def _layer_labels(wave: dict[str, Any], layers: int) -> list[str]:
    """Labels of dimension 2 (one per channel), ``""`` where the file has none."""
    all_labels = wave.get("labels") or []
    names = [_text(v) for v in all_labels[2]] if len(all_labels) > 2 else []
    # The first label names the dimension itself; the layers follow.
    names = names[1:] if len(names) == layers + 1 else names
    return (names + [""] * layers)[:layers]


def _select(labels: list[str], channel: str, path: Path) -> tuple[int, str]:
    if labels == [""]:
        return 0, channel  # a single unlabelled image: the only channel
    want = _ALIASES.get(channel.lower(), channel)
    candidates = [want]
    if not re.search(r"(re)?trace$", want, re.IGNORECASE):
        candidates.append(f"{want}Trace")
    for candidate in candidates:
        try:
            label = pick_channel(labels, candidate, where=str(path))
        except ImageFileError:
            continue
        return labels.index(label), label
    has = ", ".join(label or f"<layer {k}>" for k, label in enumerate(labels))
    raise ImageFileError(f"{path}: no channel {channel!r} in this .ibw file (has: {has})")


def _height_factor(wave: dict[str, Any], name: str, path: Path) -> float:
    header = wave["wave_header"]
    unit = _text(wave.get("data_units") or b"") or _text(header.get("dataUnits", b""))
    if unit.strip():
        return length_unit_to_nm(unit, where=f"{path}: channel {name!r} unit")
    if name.lower().startswith(_METRE_CHANNELS):
        return 1e9
    raise ImageFileError(
        f"{path}: channel {name!r} has no length unit; only height channels "
        f"({', '.join(_METRE_CHANNELS)}) are read as heights"
    )


def _parse_note(raw: Any) -> dict[str, str]:
    text = raw.decode("latin-1") if isinstance(raw, bytes) else _text(raw)
    note: dict[str, str] = {}
    for line in re.split(r"\r\n|\r|\n", text):
        key, sep, value = line.partition(":")
        if sep and key.strip() and key.strip() not in note:
            note[key.strip()] = value.strip()
    return note


def _positive_number(note: dict[str, str], key: str, path: Path) -> float | None:
    if key not in note:
        return None
    try:
        value = float(note[key])
    except ValueError:
        raise ImageFileError(f"{path}: .ibw note {key} {note[key]!r} is not a number") from None
    if not 0 < value < np.inf:
        raise ImageFileError(f"{path}: .ibw note {key} must be positive, got {note[key]!r}")
    return value


def _pixel_size(
    note: dict[str, str], wave: dict[str, Any], rows: int, cols: int, path: Path
) -> tuple[float, float] | None:
    fast = _positive_number(note, "FastScanSize", path)
    slow = _positive_number(note, "SlowScanSize", path)
    if fast is not None and slow is not None:
        return fast * 1e9 / cols, slow * 1e9 / rows
    header = wave["wave_header"]
    steps = [float(v) for v in header["sfA"][:2]]
    units = [_text(u) for u in header["dimUnits"][:2]]
    if all(u.strip() for u in units) and all(0 < s < np.inf for s in steps):
        return (
            steps[0] * length_unit_to_nm(units[0], where=f"{path}: .ibw x unit"),
            steps[1] * length_unit_to_nm(units[1], where=f"{path}: .ibw y unit"),
        )
    return None


def _note_date(note: dict[str, str], path: Path) -> datetime | None:
    date, clock = note.get("Date", "").strip(), note.get("Time", "").strip()
    if not date or not clock:
        return None
    for fmt in ("%Y-%m-%d %I:%M:%S %p", "%Y-%m-%d %H:%M:%S"):
        try:
            return datetime.strptime(f"{date} {clock}", fmt)
        except ValueError:
            continue
    raise ImageFileError(
        f"{path}: .ibw note Date/Time {date!r} {clock!r} is not YYYY-MM-DD h:mm:ss [AM|PM]"
    )

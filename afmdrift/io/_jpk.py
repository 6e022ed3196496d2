"""JPK Instruments (Bruker) image scans: ``.jpk`` (TIFF) and ``.h5-jpk`` (HDF5).

``.jpk``
    A TIFF file read with tifffile; the JPK private tags are interpreted here.
    ``AFMReader.jpk.load_jpk`` reads the same tags, but it leaves the TIFF
    file open, returns the fast-axis pixel size only, flips the rows for
    display and drops the scan rate and date, so afmdrift reads the tags
    itself. Tag numbers are those of JPK's ``JPKImageSpec.txt`` (as listed in
    AFMReader's ``default_config.yaml`` and Gwyddion's ``jpk.h``):

    * Page 0 (a thumbnail) holds the scan: ``0x8042``/``0x8043`` the grid
      lengths along the fast (u) and slow (v) axes in m, ``0x8049`` the line
      rate in Hz (lines per second, trace and retrace: ``line_time_s = 1 /
      rate``), ``0x8003`` the start date.
    * Every further page is one channel: ``0x8050`` its name (``height``,
      ``measuredHeight``, ``amplitude``...), ``0x8051`` 0 for trace and 1 for
      retrace. Raw values become physical ones through calibration slots:
      ``0x8080`` the number of slots, ``0x8081`` the name of the default slot,
      and for slot ``n`` the tags ``0x8090 + 0x30 n`` (name), ``0x80A2 + 0x30 n``
      (unit), ``0x80A3 + 0x30 n`` (``LinearScaling`` or ``NullScaling``),
      ``0x80A4``/``0x80A5 + 0x30 n`` (multiplier and offset): value = raw ×
      multiplier + offset in the slot's unit.
    * Rows are kept in stored order, which starts at the grid origin: row 0 is
      the bottom line (AFMReader flips them to show the top first). The scan
      direction is not among the documented tags, so ``scan_direction`` is
      ``None``. A start date in a form other than ``YYYY-MM-DD HH:MM:SS``
      (optionally with fractional seconds and a zone name, which is dropped)
      gives ``timestamp`` ``None`` rather than an error: the date is not needed
      to place frames when the files are read in order.

``.h5-jpk``
    An HDF5 movie read with AFMReader (``AFMReader.h5_jpk.load_h5jpk``) with
    its display flip turned off, so rows are in stored order as for ``.jpk``.
    The ``Measurement_000`` group attributes give the grid
    (``position-pattern.grid.ulength``/``vlength`` in m,
    ``ilength``/``jlength`` in pixels) and the line rate
    (``timing-settings.scanRate``, lines per second); AFMReader returns the
    height channels in nm. AFMReader reshapes every frame as ``ilength ×
    ilength``, so non-square grids are refused here with that reason. The file
    gives no absolute start time that AFMReader reads, so ``timestamp`` is
    ``None`` and frame ``i`` is ``i`` frame times after frame 0.

Channels: ``Height`` (the default) selects ``height`` trace; a vendor name
with or without ``_trace``/``_retrace`` (``measuredHeight``,
``height_retrace``) selects that channel.
"""

from __future__ import annotations

import logging
import re
import struct
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.io._afmreader import afmreader_module
from afmdrift.io._channels import pick_channel
from afmdrift.io._image import AfmImage, ImageFileError, length_unit_to_nm

__all__ = ["read_h5jpk", "read_jpk"]

_START_DATE = 0x8003
_GRID_U, _GRID_V = 0x8042, 0x8043
_LINE_RATE = 0x8049
_CHANNEL, _RETRACE = 0x8050, 0x8051
_N_SLOTS, _DEFAULT_SLOT = 0x8080, 0x8081
_SLOT_NAME, _SLOT_UNIT, _SCALING_TYPE, _MULTIPLY, _OFFSET = 0x8090, 0x80A2, 0x80A3, 0x80A4, 0x80A5
_SLOT_STRIDE = 0x30
_MAX_SLOTS = 64
#: Channels stored in metres when a slot gives no unit (AFMReader's assumption too).
_METRE_CHANNELS = ("height", "measuredheight", "amplitude")
#: Most values one file may declare (the limit of :func:`afmdrift.io.load_image`).
_MAX_VALUES = 1 << 28


def _channel_key(channel: str) -> str:
    """``Height`` → ``height_trace``; ``measuredHeight`` → ``measuredheight_trace``."""
    key = channel.strip().lower()
    if key in ("height", "topography"):
        return "height_trace"
    return key if re.search(r"_(re)?trace$", key) else f"{key}_trace"


# --------------------------------------------------------------------------- .jpk


def read_jpk(path: Path, *, channel: str) -> AfmImage:
    """Read one channel of a JPK ``.jpk`` image scan (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.jpk`` file.
    channel : str
        ``"Height"`` or a JPK channel name (see the module docstring).

    Returns
    -------
    AfmImage
        Heights in nm, shape (lines, points), row 0 the bottom line;
        ``timestamp``, ``line_time_s`` and ``frame_time_s`` when the tags give
        them.

    Raises
    ------
    ImageFileError
        Not a TIFF, no JPK tags, channel absent, a calibration slot that cannot
        be resolved, a unit that is not a length, or truncated image data.
    """
    import tifffile

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    try:
        with tifffile.TiffFile(path) as tif:
            pages = list(tif.pages)
            _check_complete(tif, pages, path)
            if not pages or _tag(pages[0], _GRID_U) is None:
                raise ImageFileError(f"{path}: not a JPK image scan (no JPK grid tags)")
            channels = {_page_channel(page, path): page for page in pages[1:]}
            want = _channel_key(channel)
            if want not in channels:
                want = pick_channel(list(channels), channel, where=str(path))
            page = channels[want]
            shape = tuple(int(v) for v in page.shape)
            if len(shape) != 2 or min(shape) == 0 or shape[0] * shape[1] > _MAX_VALUES:
                raise ImageFileError(f"{path}: channel {want!r} has shape {shape}, not an image")
            raw = np.asarray(page.asarray(), dtype=np.float64)
            factor, offset = _slot_scaling(page, want, path)
            general = pages[0]
            u_m = _positive_tag(general, _GRID_U, "grid u length", path)
            v_m = _positive_tag(general, _GRID_V, "grid v length", path)
            rate = _tag(general, _LINE_RATE)
            start = _start_date(_tag(general, _START_DATE))
    except (tifffile.TiffFileError, ValueError, OSError, EOFError, KeyError, IndexError) as err:
        raise ImageFileError(f"{path}: not a readable .jpk file ({err})") from None
    heights = raw * factor + offset
    if not np.all(np.isfinite(heights)):
        raise ImageFileError(f"{path}: channel {want!r} contains non-finite heights")
    rows, cols = heights.shape
    line_time = _line_time(rate, path)
    return AfmImage(
        heights_nm=np.ascontiguousarray(heights),
        pixel_size_nm=(u_m * 1e9 / cols, v_m * 1e9 / rows),
        path=path,
        channel=want,
        timestamp=start,
        frame_time_s=rows * line_time if line_time else None,
        line_time_s=line_time,
    )


def _check_complete(tif: Any, pages: list[Any], path: Path) -> None:
    """Refuse a partly written TIFF: strips past the end, or a last page that
    points to a next page the file does not hold (tifffile stops quietly there)."""
    size = int(tif.filehandle.size)
    for page in pages:
        for offset, count in zip(page.dataoffsets, page.databytecounts, strict=False):
            if offset + count > size:
                raise ImageFileError(
                    f"{path}: truncated .jpk file ({size} bytes; page {page.index} "
                    f"data end at {offset + count})"
                )
    if not pages:
        return
    header = tif.tiff
    fh = tif.filehandle
    fh.seek(pages[-1].offset)
    (n_tags,) = struct.unpack(header.tagnoformat, fh.read(header.tagnosize))
    fh.seek(pages[-1].offset + header.tagnosize + n_tags * header.tagsize)
    raw = fh.read(header.offsetsize)
    following = struct.unpack(header.offsetformat, raw)[0] if len(raw) == header.offsetsize else -1
    if following != 0:
        raise ImageFileError(
            f"{path}: truncated .jpk file ({size} bytes; page {pages[-1].index} points to a "
            "page past the end)"
        )


def _tag(page: Any, code: int) -> Any:
    tag = page.tags.get(code)
    if tag is None:
        return None
    value = tag.value
    return value.strip("\0 ") if isinstance(value, str) else value


def _page_channel(page: Any, path: Path) -> str:
    name = _tag(page, _CHANNEL)
    if not isinstance(name, str) or not name:
        raise ImageFileError(f"{path}: a .jpk channel page has no channel name tag (0x8050)")
    retrace = _tag(page, _RETRACE)
    is_retrace = str(retrace).strip().lower() in ("1", "true")
    return f"{name.lower()}_{'retrace' if is_retrace else 'trace'}"


def _positive_tag(page: Any, code: int, what: str, path: Path) -> float:
    value = _tag(page, code)
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ImageFileError(f"{path}: .jpk {what} (tag {code:#x}) is {value!r}") from None
    if not 0 < number < np.inf:
        raise ImageFileError(f"{path}: .jpk {what} (tag {code:#x}) must be positive, got {number}")
    return number


def _slot_scaling(page: Any, channel: str, path: Path) -> tuple[float, float]:
    """(nm per raw unit, offset in nm) of the channel's default calibration slot."""
    n_slots = _tag(page, _N_SLOTS)
    default = _tag(page, _DEFAULT_SLOT)
    if n_slots is None or default is None:
        raise ImageFileError(f"{path}: channel {channel!r} has no calibration slots")
    n = int(n_slots)
    if not 0 < n <= _MAX_SLOTS:
        raise ImageFileError(f"{path}: channel {channel!r} declares {n} calibration slots")
    names = [_tag(page, _SLOT_NAME + k * _SLOT_STRIDE) for k in range(n)]
    if default not in names:
        raise ImageFileError(
            f"{path}: channel {channel!r} default slot {default!r} is not among {names}"
        )
    base = names.index(default) * _SLOT_STRIDE
    kind = _tag(page, _SCALING_TYPE + base)
    if kind == "LinearScaling":
        multiply = float(_tag(page, _MULTIPLY + base))
        offset = float(_tag(page, _OFFSET + base))
    elif kind == "NullScaling":
        multiply, offset = 1.0, 0.0
    else:
        raise ImageFileError(
            f"{path}: channel {channel!r} slot {default!r} scaling {kind!r} is not "
            "LinearScaling or NullScaling"
        )
    unit = _tag(page, _SLOT_UNIT + base)
    if isinstance(unit, str) and unit:
        to_nm = length_unit_to_nm(unit, where=f"{path}: channel {channel!r} unit")
    elif channel.rsplit("_", 1)[0] in _METRE_CHANNELS:
        to_nm = 1e9
    else:
        raise ImageFileError(f"{path}: channel {channel!r} has no length unit")
    return multiply * to_nm, offset * to_nm


def _line_time(rate: Any, path: Path) -> float | None:
    if rate is None:
        return None
    try:
        hz = float(rate)
    except (TypeError, ValueError):
        raise ImageFileError(f"{path}: .jpk line rate (tag 0x8049) is {rate!r}") from None
    if not 0 < hz < np.inf:
        raise ImageFileError(f"{path}: .jpk line rate (tag 0x8049) must be positive, got {hz}")
    return 1.0 / hz


def _start_date(value: Any) -> datetime | None:
    if not isinstance(value, str):
        return None
    m = re.match(r"\s*(\d{4}-\d{2}-\d{2})[ T](\d{2}:\d{2}:\d{2}(?:\.\d+)?)", value)
    if m is None:
        return None
    try:
        return datetime.fromisoformat(f"{m.group(1)}T{m.group(2)}")
    except ValueError:
        return None


# --------------------------------------------------------------------------- .h5-jpk


def read_h5jpk(path: Path, *, channel: str) -> list[AfmImage]:
    """Read every frame of one channel of a JPK ``.h5-jpk`` movie (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.h5-jpk`` file.
    channel : str
        ``"Height"`` or a JPK channel name (see the module docstring).

    Returns
    -------
    list of AfmImage
        One per frame, ``frame`` = 0, 1, ..., with ``line_time_s`` and
        ``frame_time_s`` when the file gives the line rate.

    Raises
    ------
    ImageFileError
        Not HDF5, no ``Measurement_000`` grid, a non-square grid, channel
        absent or not a height, or truncated data.
    """
    import h5py

    want = _channel_key(channel)
    if want.rsplit("_", 1)[0] not in _METRE_CHANNELS:
        raise ImageFileError(
            f"{path}: channel {channel!r} is not a height channel "
            f"({', '.join(_METRE_CHANNELS)}); AFMReader gives nm for those only"
        )
    try:
        with h5py.File(path, "r") as f:
            group = f.get("Measurement_000")
            if not isinstance(group, h5py.Group):
                raise ImageFileError(f"{path}: not a JPK HDF5 file (no Measurement_000 group)")
            attrs = dict(group.attrs)
    except OSError as err:
        raise ImageFileError(f"{path}: not a readable HDF5 file ({err})") from None
    cols = _grid_int(attrs, "position-pattern.grid.ilength", path)
    rows = _grid_int(attrs, "position-pattern.grid.jlength", path)
    if rows != cols:
        raise ImageFileError(
            f"{path}: grid of {cols} × {rows} pixels; AFMReader reads square .h5-jpk grids only"
        )
    u_m = _grid_length(attrs, "position-pattern.grid.ulength", path)
    v_m = _grid_length(attrs, "position-pattern.grid.vlength", path)
    rate = attrs.get("timing-settings.scanRate")
    line_time = _line_time(rate, path) if rate is not None else None
    h5 = afmreader_module("h5_jpk")
    try:
        stack, _, _ = h5.load_h5jpk(path, want, flip_image=False)
    except ValueError as err:
        raise ImageFileError(f"{path}: {err}") from None
    frames: npt.NDArray[np.float64] = np.asarray(stack, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] == 0:
        raise ImageFileError(f"{path}: channel {want!r} holds no frames (shape {frames.shape})")
    if not np.all(np.isfinite(frames)):
        raise ImageFileError(f"{path}: channel {want!r} contains non-finite heights")
    pixel = (u_m * 1e9 / cols, v_m * 1e9 / rows)
    return [
        AfmImage(
            heights_nm=np.ascontiguousarray(frames[i]),
            pixel_size_nm=pixel,
            path=path,
            frame=i,
            channel=want,
            frame_time_s=rows * line_time if line_time else None,
            line_time_s=line_time,
        )
        for i in range(frames.shape[0])
    ]


def _grid_int(attrs: dict[str, Any], key: str, path: Path) -> int:
    try:
        value = int(attrs[key])
    except (KeyError, TypeError, ValueError):
        raise ImageFileError(f"{path}: .h5-jpk attribute {key} missing or not a number") from None
    if not 0 < value <= 1 << 14:
        raise ImageFileError(f"{path}: .h5-jpk attribute {key} = {value} is not usable")
    return value


def _grid_length(attrs: dict[str, Any], key: str, path: Path) -> float:
    try:
        value = float(attrs[key])
    except (KeyError, TypeError, ValueError):
        raise ImageFileError(f"{path}: .h5-jpk attribute {key} missing or not a number") from None
    if not 0 < value < np.inf:
        raise ImageFileError(f"{path}: .h5-jpk attribute {key} must be positive, got {value}")
    return value

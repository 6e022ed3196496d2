"""WSxM ``.stp`` images (Nanotec Electrónica / UAM): a small reader of our own.

``AFMReader.stp.load_stp`` reads these files, but it refuses scans whose x and
y sizes differ, understands only ``nm`` and ``µm`` lateral units, takes the
heights as nm whatever the header's Z unit, and converts the values one at a
time in Python. The layout is short and plain, so afmdrift reads it here.

Format (as WSxM writes it and Gwyddion's ``wsxmfile`` module and AFMReader
read it):

* A text header (ISO-8859-1) that starts with ``WSxM file copyright ...``,
  then ``SxM Image file`` and ``Image header size: N``: the header is the
  first ``N`` bytes of the file and the data start at byte ``N``.
* After that preamble, sections ``[Name]`` of ``Key: value`` lines, the last
  one ``[Header end]``. Used here: ``[General Info]`` ``Number of columns``,
  ``Number of rows``, ``Image Data Type`` (``double`` in ``.stp`` files),
  ``Z Amplitude`` (its unit is the unit of the stored values) and
  ``Acquisition channel``; ``[Control]`` ``X Amplitude`` and ``Y Amplitude``
  (the scan width and height with their unit: ``nm``, ``µm``, ``Å``...) and
  ``X Frequency`` (also spelt ``X-Frequency``: lines per second, trace and
  retrace, so ``line_time_s = 1 / frequency``).
* The data: ``rows × columns`` little-endian float64, row by row, the first
  stored row at the top of the image (both readers show it there). Rows are
  reversed here so that row 0 is the bottom line, as for the other formats.

The header carries no date or scan direction that we could verify, so
``timestamp`` and ``scan_direction`` are ``None``. A file shorter than its
header declares is refused, never read in part.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from afmdrift.io._image import AfmImage, ImageFileError, length_unit_to_nm

__all__ = ["read_stp"]

_MAGIC = b"WSxM file copyright"
_HEADER_SIZE = re.compile(rb"Image header size:\s*(\d+)")
#: Longest header read (real headers are a few kB).
_MAX_HEADER_BYTES = 1 << 20
#: Most values one file may declare (the limit of :func:`afmdrift.io.load_image`).
_MAX_VALUES = 1 << 28
_HEIGHT_CHANNELS = ("topography", "height", "topo", "z")


def read_stp(path: Path, *, channel: str) -> AfmImage:
    """Read a WSxM ``.stp`` image (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.stp`` file.
    channel : str
        ``"Height"`` (the default) accepts a topography image; another name
        must match the header's ``Acquisition channel`` (case-insensitive).

    Returns
    -------
    AfmImage
        Heights in nm, shape (rows, columns), row 0 the bottom line;
        ``line_time_s`` and ``frame_time_s`` when the header gives the line
        frequency.

    Raises
    ------
    ImageFileError
        Not a WSxM file, header without its size or end, missing or garbled
        sizes, a data type other than double, a unit that is not a length, a
        different channel, or fewer data bytes than declared.
    """
    with path.open("rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
        if not head.startswith(_MAGIC):
            raise ImageFileError(f"{path}: not a WSxM file (no 'WSxM file copyright' line)")
        m = _HEADER_SIZE.search(head[:256])
        if m is None:
            raise ImageFileError(f"{path}: WSxM header has no 'Image header size'")
        header_size = int(m.group(1))
        if not len(_MAGIC) < header_size <= _MAX_HEADER_BYTES:
            raise ImageFileError(f"{path}: WSxM 'Image header size: {header_size}' is not usable")
        if len(head) < header_size:
            raise ImageFileError(
                f"{path}: truncated WSxM file ({len(head)} bytes; the header alone is "
                f"{header_size})"
            )
        sections = _parse_header(head[:header_size].decode("latin-1"), path)
        info = sections.get("general info", {})
        control = sections.get("control", {})
        cols = _count(info, "number of columns", path)
        rows = _count(info, "number of rows", path)
        if cols * rows > _MAX_VALUES:
            raise ImageFileError(f"{path}: WSxM image of {cols} × {rows} values is too large")
        kind = info.get("image data type", "double").strip().lower()
        if kind != "double":
            raise ImageFileError(
                f"{path}: WSxM 'Image Data Type: {kind}' is not supported (.stp holds double)"
            )
        acquired = info.get("acquisition channel", "").strip()
        _check_channel(channel, acquired, path)
        need = header_size + rows * cols * 8
        size = path.stat().st_size
        if size < need:
            raise ImageFileError(
                f"{path}: truncated WSxM file ({size} bytes; the header declares {need})"
            )
        f.seek(header_size)
        raw = np.frombuffer(f.read(rows * cols * 8), dtype="<f8")
    z_value, z_unit = _quantity(info, "z amplitude", path)
    if not z_unit:
        raise ImageFileError(f"{path}: WSxM 'Z Amplitude: {z_value}' gives no unit")
    z_factor = length_unit_to_nm(z_unit, where=f"{path}: WSxM Z Amplitude unit")
    heights = raw.reshape(rows, cols)[::-1] * z_factor
    if not np.all(np.isfinite(heights)):
        raise ImageFileError(f"{path}: WSxM image contains non-finite heights")
    width = _length_nm(control, "x amplitude", path)
    height = _length_nm(control, "y amplitude", path)
    frequency = control.get("x frequency") or control.get("x-frequency")
    line_time = _line_time(frequency, path)
    return AfmImage(
        heights_nm=np.ascontiguousarray(heights),
        pixel_size_nm=(width / cols, height / rows),
        path=path,
        channel=acquired or "Topography",
        frame_time_s=rows * line_time if line_time else None,
        line_time_s=line_time,
    )


def _parse_header(text: str, path: Path) -> dict[str, dict[str, str]]:
    """``{section (lower case): {key (lower case): value}}``; the header must end."""
    sections: dict[str, dict[str, str]] = {}
    section: str | None = None
    for raw in re.split(r"\r\n|\r|\n", text):
        line = raw.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1].strip().lower()
            sections.setdefault(section, {})
        elif section is not None and ":" in line:
            key, _, value = line.partition(":")
            sections[section].setdefault(key.strip().lower(), value.strip())
    if section != "header end":
        raise ImageFileError(f"{path}: WSxM header does not end with [Header end]")
    return sections


def _count(info: dict[str, str], key: str, path: Path) -> int:
    value = info.get(key, "")
    if not re.fullmatch(r"\d+", value) or not 0 < int(value) <= 1 << 16:
        raise ImageFileError(f"{path}: WSxM header '{key}' is {value!r}, not a pixel count")
    return int(value)


def _quantity(values: dict[str, str], key: str, path: Path) -> tuple[float, str]:
    """``"12.5 nm"`` → ``(12.5, "nm")``."""
    text = values.get(key)
    if text is None:
        raise ImageFileError(f"{path}: WSxM header has no '{key}'")
    m = re.fullmatch(r"([-+]?\d+(?:[.,]\d*)?(?:[eE][-+]?\d+)?)\s*(.*)", text)
    if m is None:
        raise ImageFileError(f"{path}: WSxM header '{key}' {text!r} is not a number and unit")
    return float(m.group(1).replace(",", ".")), m.group(2).strip()


def _length_nm(values: dict[str, str], key: str, path: Path) -> float:
    number, unit = _quantity(values, key, path)
    # "Å" written by a Windows code page and read back as UTF-8 bytes.
    unit = unit.replace("Ã\x85", "Å").replace("Âµ", "µ")
    nm = number * length_unit_to_nm(unit or "?", where=f"{path}: WSxM '{key}' unit")
    if not 0 < nm < np.inf:
        raise ImageFileError(f"{path}: WSxM '{key}' must be positive, got {values[key]!r}")
    return nm


def _check_channel(channel: str, acquired: str, path: Path) -> None:
    want = channel.strip().lower()
    have = acquired.lower()
    if want == have:
        return
    if want in _HEIGHT_CHANNELS and (not have or have in _HEIGHT_CHANNELS):
        return
    raise ImageFileError(
        f"{path}: no channel {channel!r} in this WSxM file "
        f"(it holds {acquired or 'one unnamed channel'!r})"
    )


def _line_time(frequency: str | None, path: Path) -> float | None:
    if not frequency:
        return None
    m = re.match(r"\s*([-+]?\d+(?:[.,]\d*)?(?:[eE][-+]?\d+)?)\s*(Hz)?\s*$", frequency)
    if m is None:
        raise ImageFileError(f"{path}: WSxM 'X Frequency' {frequency!r} is not a frequency in Hz")
    hz = float(m.group(1).replace(",", "."))
    if not 0 < hz < np.inf:
        raise ImageFileError(f"{path}: WSxM 'X Frequency' must be positive, got {frequency!r}")
    return 1.0 / hz

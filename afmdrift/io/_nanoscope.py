"""NanoScope (Bruker / Digital Instruments) ``.spm`` and ``.000``–``.999`` files.

Heights come from AFMReader (``AFMReader.spm.load_spm``, built on pySPM), which
returns nm and wants a ``.spm`` suffix, so numbered files are copied to a
temporary ``.spm`` file first. The timing and direction fields come from the
plain-text header at the start of the file, parsed here.

Units and orientation (verified on the NanoScope IIIa v5.31 files in
``shared/data/real``):

* AFMReader's heights equal the raw 16-bit values times ``@2:Z scale`` (V/LSB)
  times ``@Sens. Zscan`` (nm/V), i.e. nm; e.g. 0.10116 nm/LSB for
  ``nanoscope3a_15um.002``. ``tests/integration/test_realdata_io.py`` checks this.
* AFMReader flips the rows for display (first row = top of the image). We undo
  that flip and keep the order in which the lines are stored in the file. The
  first stored line is the bottom of the displayed image (hence the display
  flip), and an ``Up`` frame scans bottom to top, so stored order is the order
  of acquisition for ``Frame direction: Up`` and the header's direction maps
  to :class:`ScanDirection` directly. This rests on that display convention;
  the sample files carry no independent check of the scan order.
* ``\\Scan rate`` is lines per second (trace + retrace), so
  ``line_time_s = 1 / scan rate`` and ``frame_time_s = lines / scan rate``.
* ``\\Date`` is taken as the moment the capture completed (the file is written
  when the frame ends); ``timestamp`` is that date minus ``frame_time_s``.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from afmdrift.io._afmreader import afmreader_module
from afmdrift.io._channels import pick_channel
from afmdrift.io._image import AfmImage, ImageFileError, length_unit_to_nm
from afmdrift.records import ScanDirection

__all__ = ["NanoscopeHeader", "is_nanoscope_suffix", "parse_nanoscope_header", "read_nanoscope"]

_NUMBERED = re.compile(r"^\.\d{3}$")
_HEADER_END = b"\\*File list end"
_MAX_HEADER_BYTES = 1 << 20


def is_nanoscope_suffix(suffix: str) -> bool:
    """``.spm`` or a three-digit numbered suffix (``.000``–``.999``)."""
    return suffix.lower() == ".spm" or bool(_NUMBERED.match(suffix))


class NanoscopeHeader:
    """The fields of a NanoScope text header that afmdrift uses.

    Attributes
    ----------
    entries : list of (section, key, value)
        Every ``\\key: value`` line, with the ``\\*section`` it belongs to.
    """

    def __init__(self, entries: list[tuple[str, str, str]], *, where: str) -> None:
        self.entries = entries
        self._where = where

    def first(self, key: str) -> str | None:
        """Value of the first line with ``key`` (case-insensitive), or ``None``."""
        k = key.lower()
        for _, name, value in self.entries:
            if name.lower() == k:
                return value
        return None

    def number(self, key: str) -> float | None:
        """The leading number of ``key``'s value, or ``None`` when absent."""
        value = self.first(key)
        if value is None:
            return None
        m = re.search(r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?", value)
        if m is None:
            raise ImageFileError(f"{self._where}: header \\{key} has no number: {value!r}")
        return float(m.group(0))

    def channels(self) -> list[str]:
        """Channel names of the image sections (``\\@2:Image Data: S [Height] "Height"``)."""
        names = []
        for _, name, value in self.entries:
            if name.lower().endswith("image data"):
                quoted = re.search(r'"([^"]*)"', value)
                names.append(quoted.group(1) if quoted else value.strip())
        return names

    def date(self) -> datetime | None:
        """``\\Date`` (e.g. ``12:34:38 PM Tue Jul 30 2019``) as a naive datetime."""
        value = self.first("Date")
        if value is None:
            return None
        text = " ".join(value.split())
        for fmt in ("%I:%M:%S %p %a %b %d %Y", "%H:%M:%S %a %b %d %Y"):
            try:
                return datetime.strptime(text, fmt)
            except ValueError:
                continue
        raise ImageFileError(f"{self._where}: header \\Date {value!r} is not a date")

    def scan_size_nm(self) -> tuple[float, float] | None:
        """(width, height) of the scan in nm.

        Prefers the image section's two-number form (``\\Scan size: 15 15 ~m``);
        falls back to the scan list's one-number form with ``\\Aspect ratio``.
        """
        values = [v for _, k, v in self.entries if k.lower() == "scan size"]
        if not values:
            return None
        pattern = re.compile(r"\s*([-+\d.eE]+)\s+(?:([-+\d.eE]+)\s+)?(\S+)\s*$")
        matches: list[re.Match[str]] = []
        for value in values:
            found = pattern.match(value)
            if found is None:
                raise ImageFileError(f"{self._where}: header \\Scan size {value!r} not understood")
            matches.append(found)
        two = [found for found in matches if found.group(2)]
        m = two[0] if two else matches[0]
        factor = length_unit_to_nm(m.group(3).replace("~m", "um"), where=self._where)
        width = float(m.group(1)) * factor
        if m.group(2):
            return width, float(m.group(2)) * factor
        aspect = re.match(r"\s*([\d.]+)\s*:\s*([\d.]+)", self.first("Aspect ratio") or "1:1")
        ratio = float(aspect.group(2)) / float(aspect.group(1)) if aspect else 1.0
        return width, width * ratio


def parse_nanoscope_header(path: Path) -> NanoscopeHeader:
    """Read the plain-text header at the start of a NanoScope file.

    Raises
    ------
    ImageFileError
        The file does not start with a NanoScope header (``\\*File list``) or
        the header never ends.
    """
    where = str(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(_MAX_HEADER_BYTES)
    except OSError as err:
        raise ImageFileError(f"{where}: cannot read ({err.strerror})") from None
    if not head.lstrip().startswith(b"\\*File list") and not head.startswith(b"\\*Force file list"):
        raise ImageFileError(f"{where}: not a NanoScope file (no '\\*File list' header)")
    end = head.find(_HEADER_END)
    if end < 0:
        raise ImageFileError(f"{where}: NanoScope header is truncated (no '\\*File list end')")
    text = head[:end].decode("latin-1")
    entries: list[tuple[str, str, str]] = []
    section = ""
    for raw in re.split(r"\r\n|\n|\r", text):
        line = raw.strip()
        if line.startswith("\\*"):
            section = line[2:].strip()
        elif line.startswith("\\") and ":" in line:
            # "\\@2:Image Data: S [Height] ..." -- the key ends at the first ": ".
            body = line[1:]
            cut = body.find(": ")
            key, value = (body[:cut], body[cut + 2 :]) if cut >= 0 else (body.rstrip(":"), "")
            entries.append((section, key.strip(), value.strip()))
    return NanoscopeHeader(entries, where=where)


def read_nanoscope(path: Path, *, channel: str) -> AfmImage:
    """Read one channel of a NanoScope file as an :class:`AfmImage` (heights in nm).

    Parameters
    ----------
    path : Path
        ``.spm`` or numbered (``.000``–``.999``) NanoScope file.
    channel : str
        Image channel name as in the header's ``Image Data`` line, e.g. ``"Height"``.

    Raises
    ------
    ImageFileError
        Not a NanoScope file, the channel is absent, or the data are truncated.
    """
    header = parse_nanoscope_header(path)
    channel = pick_channel(header.channels(), channel, where=str(path))
    spm = afmreader_module("spm")
    with tempfile.TemporaryDirectory(prefix="afmdrift-spm-") as tmp:
        copy = Path(tmp) / "image.spm"
        shutil.copyfile(path, copy)
        try:
            display, pixel_nm = spm.load_spm(copy, channel)
        except Exception as err:  # pySPM raises bare Exceptions on corrupt data
            raise ImageFileError(f"{path}: cannot read channel {channel!r} ({err})") from None
    heights = np.ascontiguousarray(np.flipud(np.asarray(display, dtype=np.float64)))
    if heights.ndim != 2 or heights.size == 0:
        raise ImageFileError(f"{path}: channel {channel!r} holds no 2-D image")
    if not np.all(np.isfinite(heights)):
        raise ImageFileError(f"{path}: channel {channel!r} contains non-finite heights")
    rows, cols = heights.shape
    size = header.scan_size_nm()
    if size is not None:
        pixel = (size[0] / cols, size[1] / rows)
    else:
        pixel = (float(pixel_nm), float(pixel_nm))
    rate_hz = header.number("Scan rate")
    line_time = 1.0 / rate_hz if rate_hz else None
    frame_time = rows * line_time if line_time else None
    date = header.date()
    timestamp = date - timedelta(seconds=frame_time) if date and frame_time else date
    direction_text = (header.first("Frame direction") or "").strip().lower()
    direction = ScanDirection(direction_text) if direction_text in ("up", "down") else None
    return AfmImage(
        heights_nm=heights,
        pixel_size_nm=pixel,
        path=path,
        channel=channel,
        timestamp=timestamp,
        frame_time_s=frame_time,
        line_time_s=line_time,
        scan_direction=direction,
    )

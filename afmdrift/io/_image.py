"""The in-memory image record returned by every reader, and its errors."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.errors import InputError
from afmdrift.records import ScanDirection

__all__ = [
    "MAX_HEIGHT_RANGE_NM",
    "MAX_PIXEL_NM",
    "MAX_SCAN_NM",
    "MIN_PIXEL_NM",
    "AfmImage",
    "ImageFileError",
    "check_calibration",
    "height_factor_nm",
    "length_unit_to_nm",
]

#: Plausible bounds of a header calibration. AFM pixels range from a few pm
#: (atomic resolution) to tens of µm (a 100 µm scan at a few px); scanners move
#: at most ~200 µm laterally and ~20 µm in z. A value outside these bounds is a
#: corrupt header field, not a measurement: an ``.asd`` header field corrupted
#: to 2.14e9 nm gives a 10.7 mm pixel and a drift of millimetres.
MIN_PIXEL_NM = 1e-3
MAX_PIXEL_NM = 1e5
MAX_SCAN_NM = 1e6
MAX_HEIGHT_RANGE_NM = 1e5


class ImageFileError(InputError):
    """An image file cannot be read: missing, unknown suffix, corrupt, wrong channel
    or frame index. The message names the file and the problem."""


class MissingPixelSizeError(ImageFileError):
    """The file carries no usable pixel size (a bare array, a channel without
    a lateral unit, an implausible calibration), and none was given."""


@dataclass(frozen=True, slots=True)
class AfmImage:
    """One height image read from a file.

    Attributes
    ----------
    heights_nm : ndarray, shape (rows, cols), float64
        Heights in nm. x runs along columns (fast axis), y along rows.
    pixel_size_nm : (float, float)
        Pixel size along x (columns) and y (rows) in nm.
    path : Path
        The file the image came from.
    frame : int or None
        Frame index inside a multi-frame file (``.asd`` movie, 3-D ``.npy``), else ``None``.
    channel : str
        The channel actually read (for example ``"Height"``, ``"TP"``).
    timestamp : datetime or None
        Start of this frame's scan when the header gives a date (naive local
        time as written by the instrument), else ``None``. See
        ``docs/session-format.md`` and the reader docstrings for what each
        format's date marks.
    frame_time_s : float or None
        Time to scan the whole frame, when the header gives it.
    line_time_s : float or None
        Time per scan line (trace and retrace), when the header gives it.
    scan_direction : ScanDirection or None
        Slow-axis direction in the stored row order, when the header gives it.
    """

    heights_nm: npt.NDArray[np.float64]
    pixel_size_nm: tuple[float, float]
    path: Path
    frame: int | None = None
    channel: str = "Height"
    timestamp: datetime | None = None
    frame_time_s: float | None = None
    line_time_s: float | None = None
    scan_direction: ScanDirection | None = None

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.heights_nm.shape
        return int(rows), int(cols)

    @property
    def source(self) -> str:
        """``path`` or ``path:frame`` — the spec that reads this image again."""
        return str(self.path) if self.frame is None else f"{self.path}:{self.frame}"


#: Length units accepted in file headers and options, as nm per unit.
_LENGTH_UNITS_NM: dict[str, float] = {
    "m": 1e9,
    "mm": 1e6,
    "um": 1e3,
    "µm": 1e3,
    "μm": 1e3,
    "micron": 1e3,
    "microns": 1e3,
    "nm": 1.0,
    "a": 0.1,
    "å": 0.1,
    "angstrom": 0.1,
    "pm": 1e-3,
}


def length_unit_to_nm(unit: str, *, where: str) -> float:
    """Nanometres per ``unit`` (m, mm, um/µm/micron, nm, Å/A/angstrom, pm).

    Raises
    ------
    ImageFileError
        ``unit`` is empty or not a length; the message starts with ``where``.
    """
    key = unit.strip()
    factor = _LENGTH_UNITS_NM.get(key) or _LENGTH_UNITS_NM.get(key.lower())
    if factor is None:
        known = ", ".join(sorted({k for k in _LENGTH_UNITS_NM if k.isascii()}))
        raise ImageFileError(f"{where}: unit {unit!r} is not a length unit (known: {known})")
    return factor


def height_factor_nm(file_unit: str, height_unit: str | None, *, where: str) -> float:
    """Nanometres per stored height value.

    ``file_unit`` is the unit the file declares (``""`` when it declares none);
    ``height_unit`` is the caller's unit for files that declare none.

    Raises
    ------
    ImageFileError
        Neither gives a unit, or the unit is not a length; names ``where``.
    """
    if file_unit:
        return length_unit_to_nm(file_unit, where=f"{where} height unit")
    if height_unit is not None:
        return length_unit_to_nm(height_unit, where="height_unit")
    raise ImageFileError(
        f"{where}: heights have no unit; give the height unit (height_unit=..., --height-unit)"
    )


def check_calibration(image: AfmImage, *, what: str = "pixel size", heights: bool = True) -> None:
    """Refuse a calibration outside plausible AFM bounds (see :data:`MAX_SCAN_NM`);
    ``heights=False`` checks the pixel size only (no pass over the heights).

    Raises
    ------
    ImageFileError
        Names the file, the quantity (``what``, e.g. a header field), its value
        and the bounds.
    """
    where = image.source
    rows, cols = image.shape
    for axis, pixel, n in (
        ("x", image.pixel_size_nm[0], cols),
        ("y", image.pixel_size_nm[1], rows),
    ):
        if not (MIN_PIXEL_NM <= pixel <= MAX_PIXEL_NM and pixel * n <= MAX_SCAN_NM):
            raise MissingPixelSizeError(
                f"{where}: implausible {what} along {axis}: {pixel:.4g} nm per pixel "
                f"({pixel * n:.4g} nm over {n} px); an AFM pixel is {MIN_PIXEL_NM:g} to "
                f"{MAX_PIXEL_NM:g} nm and a scan at most {MAX_SCAN_NM:g} nm: the header "
                "calibration is corrupt (or give pixel_size_nm / --pixel-size-nm)"
            )
    if not heights:
        return
    span = float(np.ptp(image.heights_nm)) if image.heights_nm.size else 0.0
    if not span <= MAX_HEIGHT_RANGE_NM:
        raise ImageFileError(
            f"{where}: implausible height range {span:.4g} nm (an AFM's z range is at most "
            f"{MAX_HEIGHT_RANGE_NM:g} nm): the header's height scale or unit is corrupt"
        )

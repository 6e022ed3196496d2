"""Gwyddion native files (``.gwy``, the ``GWYP`` serialisation).

Parsed here from the published format description (Gwyddion user guide,
"GWY File Format"): after the magic ``GWYP`` comes one serialised object,
``name\\0``, ``uint32`` byte size, then components ``name\\0``, one type byte
and the value (little-endian; ``b c i q d s o`` scalars, ``C I Q D S O``
arrays preceded by a ``uint32`` count). A ``GwyContainer`` holds channels as
``/N/data`` (a ``GwyDataField``) with titles ``/N/data/title``.

We parse it ourselves rather than through ``AFMReader.gwy`` because that
reader reshapes the data as (xres, yres) (wrong for non-square fields: the
data are row-major, ``yres`` rows of ``xres`` values), reads the height unit
from ``si_unit_xy`` instead of ``si_unit_z``, and rejects unitless fields.

Units: ``xreal``/``yreal`` are in ``si_unit_xy`` and heights in ``si_unit_z``
(Gwyddion writes base SI, ``m``). A field without a lateral unit needs
``pixel_size_nm``; one without a height unit needs ``height_unit``.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

from afmdrift.io._image import (
    AfmImage,
    ImageFileError,
    MissingPixelSizeError,
    height_factor_nm,
    length_unit_to_nm,
)

__all__ = ["gwy_channels", "read_gwy"]

_MAGIC = b"GWYP"
_SCALARS = {"b": ("<?", 1), "c": ("<c", 1), "i": ("<i", 4), "q": ("<q", 8), "d": ("<d", 8)}
_ARRAYS = {"C": ("u1", 1), "I": ("<i4", 4), "Q": ("<i8", 8), "D": ("<f8", 8)}


class _TruncatedError(Exception):
    """Internal: the byte stream ended inside an object."""


class _Parser:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, n: int) -> bytes:
        end = self.pos + n
        if n < 0 or end > len(self.data):
            raise _TruncatedError
        chunk = self.data[self.pos : end]
        self.pos = end
        return chunk

    def string(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise _TruncatedError
        text = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return text

    def u32(self) -> int:
        return int(struct.unpack("<I", self.take(4))[0])

    def obj(self) -> dict[str, Any]:
        type_name = self.string()
        size = self.u32()
        end = self.pos + size
        if end > len(self.data):
            raise _TruncatedError
        out: dict[str, Any] = {"__type__": type_name}
        while self.pos < end:
            name = self.string()
            out[name] = self.value(self.take(1).decode("latin-1"))
        if self.pos != end:
            raise _TruncatedError
        return out

    def value(self, kind: str) -> Any:
        if kind in _SCALARS:
            fmt, n = _SCALARS[kind]
            return struct.unpack(fmt, self.take(n))[0]
        if kind == "s":
            return self.string()
        if kind == "o":
            return self.obj()
        count = self.u32()
        if kind in _ARRAYS:
            dtype, n = _ARRAYS[kind]
            return np.frombuffer(self.take(count * n), dtype=dtype).copy()
        if kind == "S":
            return [self.string() for _ in range(count)]
        if kind == "O":
            return [self.obj() for _ in range(count)]
        raise ValueError(f"unknown component type {kind!r} at byte {self.pos - 1}")


def _container(path: Path) -> dict[str, Any]:
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ImageFileError(f"{path}: cannot read ({err.strerror})") from None
    if not data.startswith(_MAGIC):
        raise ImageFileError(f"{path}: not a Gwyddion file (no 'GWYP' magic)")
    parser = _Parser(data)
    parser.pos = len(_MAGIC)
    try:
        return parser.obj()
    except _TruncatedError:
        raise ImageFileError(f"{path}: Gwyddion file is truncated or corrupt") from None
    except ValueError as err:
        raise ImageFileError(f"{path}: Gwyddion file is corrupt ({err})") from None


def gwy_channels(container: dict[str, Any]) -> dict[str, str]:
    """Map channel title → container key (``"/0/data"``) for every data field."""
    out: dict[str, str] = {}
    for key, value in container.items():
        if (
            key.startswith("/")
            and key.endswith("/data")
            and isinstance(value, dict)
            and value.get("__type__") == "GwyDataField"
        ):
            title = container.get(f"{key}/title")
            out[str(title) if isinstance(title, str) and title else key] = key
    return out


def _unit(field: dict[str, Any], name: str) -> str:
    unit = field.get(name)
    return str(unit.get("unitstr", "")) if isinstance(unit, dict) else ""


def read_gwy(
    path: Path,
    *,
    channel: str,
    pixel_size_nm: tuple[float, float] | None,
    height_unit: str | None,
) -> AfmImage:
    """Read one data field of a ``.gwy`` file (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.gwy`` file.
    channel : str
        Channel title. ``"Height"`` (the default everywhere) also matches a
        title containing "height" or "topo", or the only channel of a file.
    pixel_size_nm : (float, float) or None
        Overrides the file's lateral calibration; required when the field has
        no lateral unit.
    height_unit : str or None
        Unit of the heights when the field has none (e.g. ``"nm"``).

    Raises
    ------
    ImageFileError
        Not a Gwyddion file, truncated, channel absent, or units missing.
    """
    container = _container(path)
    channels = gwy_channels(container)
    key = _pick_channel(channels, channel, path)
    field = container[key]
    title = next(t for t, k in channels.items() if k == key)
    xres, yres = int(field.get("xres", 0)), int(field.get("yres", 0))
    data = field.get("data")
    if not isinstance(data, np.ndarray) or xres <= 0 or yres <= 0 or data.size != xres * yres:
        raise ImageFileError(f"{path}: channel {title!r} has no {yres}x{xres} data array")
    z_factor = height_factor_nm(
        _unit(field, "si_unit_z"), height_unit, where=f"{path}: channel {title!r}"
    )
    heights = data.astype(np.float64).reshape(yres, xres) * z_factor
    if not np.all(np.isfinite(heights)):
        raise ImageFileError(f"{path}: channel {title!r} contains non-finite heights")
    if pixel_size_nm is None:
        xy_unit = _unit(field, "si_unit_xy")
        if not xy_unit:
            raise MissingPixelSizeError(
                f"{path}: channel {title!r} has no lateral unit "
                f"(xreal={field.get('xreal')}); give pixel_size_nm (--pixel-size-nm)"
            )
        factor = length_unit_to_nm(xy_unit, where=f"{path}: channel {title!r} lateral")
        pixel_size_nm = (
            float(field["xreal"]) * factor / xres,
            float(field["yreal"]) * factor / yres,
        )
    return AfmImage(heights_nm=heights, pixel_size_nm=pixel_size_nm, path=path, channel=title)


def _pick_channel(channels: dict[str, str], channel: str, path: Path) -> str:
    if not channels:
        raise ImageFileError(f"{path}: Gwyddion file holds no data field")
    if channel in channels:
        return channels[channel]
    if channel.lower() == "height":
        hits = [k for t, k in channels.items() if "height" in t.lower() or "topo" in t.lower()]
        if len(hits) == 1:
            return hits[0]
        if len(channels) == 1:
            return next(iter(channels.values()))
    raise ImageFileError(
        f"{path}: channel {channel!r} not in this Gwyddion file (has: {', '.join(channels)})"
    )

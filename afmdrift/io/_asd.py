"""High-speed AFM movies (``.asd``, Ando lab / RIBM format, file versions 0–2).

Heights come from AFMReader (``AFMReader.asd.load_asd``). Its topography
(``TP``) conversion is raw level × (−AD range / 4096) × Z piezo extension
(nm/V) × Z piezo gain, i.e. nm; the pixel size is the header's scan range in
nm over the pixel count, per axis. The header's ``frame_time`` is in ms
(1000.0 for the 1 s/frame sample movie). The header date is taken as the start
of frame 0; frame ``i`` starts ``i × frame_time`` later. The header's
``scan_direction`` code is not documented well enough to map to up/down, so
``scan_direction`` is left ``None``.
"""

from __future__ import annotations

import struct
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.io._afmreader import afmreader_module
from afmdrift.io._image import AfmImage, ImageFileError, check_calibration

__all__ = ["read_asd"]

#: "Height" is accepted as the name of the topography channel.
_ALIASES = {"height": "TP", "topography": "TP", "error": "ER", "phase": "PH"}


def read_asd(path: Path, *, channel: str) -> list[AfmImage]:
    """Read every frame of one channel of an ``.asd`` movie (heights in nm).

    Parameters
    ----------
    path : Path
        The ``.asd`` file.
    channel : str
        ``"TP"`` (topography; ``"Height"`` is an alias), ``"ER"`` or ``"PH"``.

    Returns
    -------
    list of AfmImage
        One per frame, ``frame`` = 0, 1, ..., each with ``timestamp`` and
        ``frame_time_s`` (the header gives no line time).

    Raises
    ------
    ImageFileError
        Unknown version, channel not in the file, or truncated frame data.
    """
    code = _ALIASES.get(channel.lower(), channel)
    asd = afmreader_module("asd")
    try:
        frames, _, header = asd.load_asd(path, code)
    except ValueError as err:
        if "channel" in str(err) or "not found" in str(err):  # AFMReader's wrong-channel error
            raise ImageFileError(f"{path}: {err}") from None
        raise ImageFileError(f"{path}: truncated or corrupt .asd data ({err})") from None
    except (struct.error, EOFError, UnicodeDecodeError, IndexError, KeyError) as err:
        raise ImageFileError(f"{path}: not a readable .asd file ({type(err).__name__})") from None
    stack = np.asarray(frames, dtype=np.float64)
    n = int(header.get("num_frames", 0))
    if stack.ndim != 3 or stack.shape[0] != n or n == 0:
        raise ImageFileError(f"{path}: expected {n} frames, read array of shape {stack.shape}")
    pixel = (
        _positive(header, "x_nm", path) / stack.shape[2],
        _positive(header, "y_nm", path) / stack.shape[1],
    )
    frame_time_s = _positive(header, "frame_time", path) * 1e-3
    start = _header_date(header, path)
    check_calibration(
        AfmImage(heights_nm=stack[0], pixel_size_nm=pixel, path=path),
        what=f"calibration (header fields x_nm = {header['x_nm']}, y_nm = {header['y_nm']})",
    )
    return [
        AfmImage(
            heights_nm=_finite(stack[i], path, i),
            pixel_size_nm=pixel,
            path=path,
            frame=i,
            channel=code,
            timestamp=start + timedelta(seconds=i * frame_time_s) if start else None,
            frame_time_s=frame_time_s,
        )
        for i in range(n)
    ]


def _positive(header: dict[str, Any], key: str, path: Path) -> float:
    value = float(header.get(key, 0.0))
    if not value > 0:
        raise ImageFileError(f"{path}: header field {key} must be positive, got {value}")
    return value


def _finite(image: npt.NDArray[np.float64], path: Path, i: int) -> npt.NDArray[np.float64]:
    if not np.all(np.isfinite(image)):
        raise ImageFileError(f"{path}:{i}: frame contains non-finite heights")
    return np.ascontiguousarray(image)


def _header_date(header: dict[str, Any], path: Path) -> datetime | None:
    keys = ("year", "month", "day", "hour", "minute", "second")
    if not all(k in header for k in keys):
        return None
    try:
        y, mo, d, h, mi, sec = (int(header[k]) for k in keys)
        return datetime(y, mo, d, h, mi, sec)
    except ValueError:
        raise ImageFileError(
            f"{path}: header date {[header[k] for k in keys]} is not a valid date"
        ) from None

"""Writers for simulator frames saved as an instrument's software would save them.

The folder instrument (``folder:PATH``) reads files that vendor software
writes; its tests and benchmark need such files with known heights,
calibration and timing. :func:`write_tif` writes an ImageJ TIFF that
:func:`~afmdrift.io.load_image` reads back with its calibration and timing;
:func:`~afmdrift.io.write_sxm` (``afmdrift/io/_sxm.py``) a Nanonis ``.sxm``.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.records import ScanDirection

__all__ = ["write_tif"]


def write_tif(
    path: str | Path,
    heights_nm: npt.ArrayLike,
    *,
    pixel_size_nm: tuple[float, float],
    start: datetime | None = None,
    line_time_s: float | None = None,
    direction: ScanDirection = ScanDirection.UP,
) -> Path:
    """Write one height image as an ImageJ TIFF (float32 heights in nm).

    The pixel size goes in the X/YResolution tags with the ImageJ ``unit`` ``nm``;
    the timing in the ImageJ description as ``start_time`` (ISO-8601, start of
    the scan), ``line_time_s`` and ``scan_direction``, the keys of afmdrift's
    NetCDF convention (``docs/session-format.md``). Row 0 is the bottom line
    of the frame whatever the direction.
    """
    import tifffile

    image = np.asarray(heights_nm, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(f"heights_nm must be 2-D, got shape {image.shape}")
    metadata: dict[str, object] = {"unit": "nm", "scan_direction": direction.value}
    if start is not None:
        metadata["start_time"] = start.isoformat()
    if line_time_s is not None:
        metadata["line_time_s"] = float(line_time_s)
    p = Path(path)
    tifffile.imwrite(
        p,
        image,
        imagej=True,
        resolution=(1.0 / pixel_size_nm[0], 1.0 / pixel_size_nm[1]),
        metadata=metadata,
    )
    return p

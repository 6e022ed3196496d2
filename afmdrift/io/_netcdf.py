"""NetCDF height files: NetCDF-3 read with ``scipy.io.netcdf_file``, NetCDF-4 with h5py.

There is no single AFM convention for NetCDF, so afmdrift reads this simple one
(``docs/session-format.md`` has it with an example; any tool can write it):

* A variable named after the channel (``Height`` by default; matched exactly,
  then ignoring case, spaces, ``_`` and ``-``; the default also takes a
  height channel of another name, such as afspm's ``HeightRetrace``, see
  :func:`afmdrift.io.pick_channel`), with dimensions ``(y, x)`` for one image or
  ``(frame, y, x)`` for a stack. Rows are y, columns x (fast axis).
* Its ``units`` attribute is a length unit (``m``, ``um``, ``nm``, ``pm``,
  ``Å``...). Without it the caller must give ``height_unit``.
* Pixel size: 1-D coordinate variables named after the two image dimensions
  (e.g. ``x``, ``y``), evenly spaced, with a ``units`` attribute. Without them
  the caller must give ``pixel_size_nm``.
* Optional: a 1-D variable ``time`` along the frame dimension (``units`` ``s``,
  start of each frame's scan), global attributes ``start_time`` (ISO-8601, the
  start of frame 0), ``line_time_s`` (s per line) and ``scan_direction``
  (``up``/``down``).

NetCDF-4 files (what afspm and xarray write by default) are HDF5 files and
are read with h5py: the variable is a dataset of the root group, its dimension
names those of the dimension scales netCDF-4 attaches to it, attributes as
above (byte strings decoded). A file is taken as NetCDF-4 when it starts with
the HDF5 signature.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.io._channels import pick_channel
from afmdrift.io._image import (
    AfmImage,
    ImageFileError,
    MissingPixelSizeError,
    height_factor_nm,
    length_unit_to_nm,
)
from afmdrift.records import ScanDirection

__all__ = ["read_netcdf"]


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray) and value.dtype.kind == "S":
        return b"".join(value.tolist()).decode("utf-8", errors="replace")
    return str(value)


def read_netcdf(
    path: Path,
    *,
    channel: str,
    pixel_size_nm: tuple[float, float] | None,
    height_unit: str | None,
) -> list[AfmImage]:
    """Read every frame of a NetCDF-3 height file (see the module docstring).

    Returns
    -------
    list of AfmImage
        One element for a 2-D variable (``frame`` = ``None``), else one per frame.

    Raises
    ------
    ImageFileError
        Not NetCDF-3, variable absent, wrong dimensions, or units missing.
    """
    with path.open("rb") as f:
        is_hdf5 = f.read(8) == _HDF5_SIGNATURE
    read = _read_hdf5 if is_hdf5 else _read_nc3
    name, dims, data, attrs, globals_, coords, times = read(path, channel)
    if data.ndim not in (2, 3) or min(data.shape) == 0:
        raise ImageFileError(
            f"{path}: variable {name!r} must have dimensions (y, x) or (frame, y, x), got {dims}"
        )
    z_factor = height_factor_nm(
        attrs.get("units", ""), height_unit, where=f"{path}: variable {name!r}"
    )
    stack = (data if data.ndim == 3 else data[np.newaxis]) * z_factor
    if not np.all(np.isfinite(stack)):
        raise ImageFileError(f"{path}: variable {name!r} contains non-finite heights")
    if pixel_size_nm is None:
        pixel_size_nm = _pixel_from_coords(coords, dims, path)
    start = _start_time(globals_.get("start_time"), path)
    line_time = float(globals_["line_time_s"]) if "line_time_s" in globals_ else None
    direction_text = globals_.get("scan_direction", "").strip().lower()
    direction = ScanDirection(direction_text) if direction_text in ("up", "down") else None
    if times is not None and times.shape != (stack.shape[0],):
        raise ImageFileError(
            f"{path}: 'time' has {times.size} values for {stack.shape[0]} frame(s)"
        )
    frame_time = line_time * stack.shape[1] if line_time is not None else None
    out = []
    for i in range(stack.shape[0]):
        t0 = float(times[i] - times[0]) if times is not None else 0.0
        out.append(
            AfmImage(
                heights_nm=np.ascontiguousarray(stack[i]),
                pixel_size_nm=pixel_size_nm,
                path=path,
                frame=i if data.ndim == 3 else None,
                channel=name,
                timestamp=start + timedelta(seconds=t0) if start else None,
                frame_time_s=frame_time,
                line_time_s=line_time,
                scan_direction=direction,
            )
        )
    return out


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"

#: name, dimensions, data, variable attributes, global attributes,
#: {dimension: (coordinate values, units)}, frame times.
_Contents = tuple[
    str,
    tuple[str, ...],
    npt.NDArray[np.float64],
    dict[str, str],
    dict[str, str],
    dict[str, tuple[npt.NDArray[np.float64], str]],
    npt.NDArray[np.float64] | None,
]


def _read_nc3(path: Path, channel: str) -> _Contents:
    from scipy.io import netcdf_file

    try:
        nc = netcdf_file(path, "r", mmap=False)
    except (OSError, TypeError, ValueError, IndexError) as err:
        raise ImageFileError(f"{path}: not a readable NetCDF-3 file ({err})") from None
    with nc:
        variables: dict[str, Any] = dict(nc.variables)
        name = _pick(variables, channel, path)
        var = variables[name]
        dims = tuple(var.dimensions)
        data = np.array(var.data, dtype=np.float64)
        attrs = {k: _text(v) for k, v in var._attributes.items()}
        globals_ = {k: _text(v) for k, v in nc._attributes.items()}
        coords = {
            d: (np.array(variables[d].data, dtype=np.float64), _text(variables[d].units))
            for d in dims[-2:]
            if d in variables and hasattr(variables[d], "units")
        }
        times = np.array(variables["time"].data, dtype=np.float64) if "time" in variables else None
    return name, dims, data, attrs, globals_, coords, times


def _read_hdf5(path: Path, channel: str) -> _Contents:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ImageFileError(f"{path}: not a readable NetCDF-4/HDF5 file ({err})") from None
    with f:
        variables = {k: v for k, v in f.items() if isinstance(v, h5py.Dataset)}
        name = _pick(variables, channel, path)
        ds = variables[name]
        _check_values(path, ds.shape)
        dims = tuple(
            ds.dims[i][0].name.rsplit("/", 1)[-1] if len(ds.dims[i]) else f"dim{i}"
            for i in range(ds.ndim)
        )
        data = np.array(ds[()], dtype=np.float64)
        attrs = {k: _text(v) for k, v in ds.attrs.items() if not k.isupper()}
        globals_ = {k: _text(v) for k, v in f.attrs.items()}
        coords = {
            d: (np.array(variables[d][()], dtype=np.float64), _text(variables[d].attrs["units"]))
            for d in dims[-2:]
            if d in variables and "units" in variables[d].attrs
        }
        times = np.array(variables["time"][()], dtype=np.float64) if "time" in variables else None
    return name, dims, data, attrs, globals_, coords, times


def _check_values(path: Path, shape: tuple[int, ...]) -> None:
    n = 1
    for v in shape:
        n *= int(v)
    if n > _MAX_VALUES:
        raise ImageFileError(
            f"{path}: declares {n} values (shape {shape}); the limit is {_MAX_VALUES}"
        )


#: As :data:`afmdrift.io._load.MAX_VALUES`.
_MAX_VALUES = 1 << 28


def _pick(variables: dict[str, Any], channel: str, path: Path) -> str:
    return pick_channel(list(variables), channel, where=str(path), what="variable")


def _pixel_from_coords(
    coords: dict[str, tuple[npt.NDArray[np.float64], str]], dims: tuple[str, ...], path: Path
) -> tuple[float, float]:
    sizes = []
    for dim in (dims[-1], dims[-2]):
        if dim not in coords:
            raise MissingPixelSizeError(
                f"{path}: no coordinate variable {dim!r} with 'units'; give pixel_size_nm "
                "(--pixel-size-nm)"
            )
        values, unit = coords[dim]
        step = np.diff(values)
        if values.size < 2 or not np.allclose(step, step[0], rtol=1e-6) or step[0] == 0:
            raise ImageFileError(f"{path}: coordinate {dim!r} is not evenly spaced")
        sizes.append(abs(float(step[0])) * length_unit_to_nm(unit, where=f"{path}: {dim}.units"))
    return sizes[0], sizes[1]


def _start_time(text: str | None, path: Path) -> datetime | None:
    if not text:
        return None
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        raise ImageFileError(f"{path}: start_time {text!r} is not ISO-8601") from None

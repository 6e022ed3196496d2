"""``load_image`` / ``load_stack``: pick the reader from the file suffix.

Formats
-------
``.npy``
    2-D (one image) or 3-D (N, rows, cols) array; heights taken as nm unless
    ``height_unit`` says otherwise; ``pixel_size_nm`` is required.
``.tif`` / ``.tiff``
    2-D page or 3-D stack read with tifffile; heights as for ``.npy``. The pixel
    size comes from the ImageJ ``unit`` metadata with the X/YResolution tags,
    or from X/YResolution in cm or inch when that gives a pixel below 10 µm
    (larger values are printing defaults such as 72 dpi, not calibrations);
    otherwise ``pixel_size_nm`` is required. Timing from the ImageJ description
    keys ``start_time`` (ISO-8601), ``line_time_s`` and ``scan_direction``
    (``up``/``down``), as :func:`afmdrift.io.write_tif` writes them.
``.sxm``
    Nanonis scan, see :mod:`afmdrift.io._sxm`.
``.spm``, ``.000``–``.999``
    NanoScope, see :mod:`afmdrift.io._nanoscope`.
``.gwy``
    Gwyddion, see :mod:`afmdrift.io._gwyddion`.
``.asd``
    HS-AFM movie, see :mod:`afmdrift.io._asd`.
``.nc``
    NetCDF-3, see :mod:`afmdrift.io._netcdf`.
``.ibw``
    Asylum Research Igor binary wave, see :mod:`afmdrift.io._ibw`.
``.jpk``, ``.h5-jpk``
    JPK (Bruker) image scan (TIFF) and HDF5 movie, see :mod:`afmdrift.io._jpk`.
``.stp``
    WSxM image, see :mod:`afmdrift.io._wsxm`.

A spec ``FILE:i`` selects frame ``i`` of a multi-frame file.

Every image read is checked against plausible AFM bounds
(:func:`~afmdrift.io._image.check_calibration`: 1 pm to 100 µm per pixel, a
scan of at most 1 mm, a height range of at most 100 µm); a corrupt header
calibration gives :class:`ImageFileError` naming the value.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from afmdrift.io._asd import read_asd
from afmdrift.io._gwyddion import read_gwy
from afmdrift.io._ibw import read_ibw
from afmdrift.io._image import (
    AfmImage,
    ImageFileError,
    MissingPixelSizeError,
    check_calibration,
    length_unit_to_nm,
)
from afmdrift.io._jpk import read_h5jpk, read_jpk
from afmdrift.io._nanoscope import is_nanoscope_suffix, read_nanoscope
from afmdrift.io._netcdf import read_netcdf
from afmdrift.io._sxm import read_sxm
from afmdrift.io._wsxm import read_stp
from afmdrift.records import ScanDirection

__all__ = [
    "SINGLE_IMAGE_SUFFIXES",
    "SUFFIXES",
    "PixelSize",
    "calibrated",
    "holds_one_image",
    "is_image_file",
    "load_image",
    "load_stack",
    "parse_spec",
]

T = TypeVar("T")

#: Suffixes understood by :func:`load_image` (plus ``.000``–``.999``).
SUFFIXES = (
    ".npy",
    ".tif",
    ".tiff",
    ".spm",
    ".gwy",
    ".asd",
    ".nc",
    ".sxm",
    ".ibw",
    ".jpk",
    ".h5-jpk",
    ".stp",
)

#: Suffixes of the formats whose file holds one image (NanoScope also
#: ``.000``–``.999``): a recording of them is a series of files, one per frame.
SINGLE_IMAGE_SUFFIXES = (".spm", ".gwy", ".sxm", ".ibw", ".jpk", ".stp")

#: A pixel size in nm: one number for square pixels or ``(x, y)``.
PixelSize = float | Sequence[float]

#: Most heights read from one file (2 GiB as float64): an 8192² image is
#: 67 M, a 1000-frame 256² HS-AFM movie 66 M. A header declaring more is
#: refused before anything is allocated.
MAX_VALUES = 1 << 28

_FRAME_SPEC = re.compile(r"^(?P<path>.+):(?P<frame>-?\d+)$")
_MAX_CALIBRATED_PIXEL_NM = 1e4


def parse_spec(spec: str | Path) -> tuple[Path, int | None]:
    """Split ``FILE:i`` into ``(Path(FILE), i)``; a plain path gives ``(path, None)``."""
    text = str(spec)
    m = _FRAME_SPEC.match(text)
    if m is None or Path(text).exists():
        return Path(text), None
    return Path(m.group("path")), int(m.group("frame"))


def is_image_file(path: str | Path) -> bool:
    """``path`` is a file whose suffix :func:`load_image` reads."""
    p = Path(path)
    suffix = p.suffix.lower()
    return p.is_file() and (suffix in SUFFIXES or is_nanoscope_suffix(suffix))


def holds_one_image(path: str | Path) -> bool:
    """``path`` holds one image, not a stack or a movie: a format of one image
    per file (:data:`SINGLE_IMAGE_SUFFIXES`, NanoScope ``.000``–``.999``) or a
    2-D ``.npy`` or ``.tif`` array, told from its header alone. False for a
    file it cannot tell (its reader names the fault when it is read)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in SINGLE_IMAGE_SUFFIXES or is_nanoscope_suffix(suffix):
        return True
    if suffix == ".npy":
        try:
            return int(np.load(p, mmap_mode="r", allow_pickle=False).ndim) == 2
        except (ValueError, OSError, EOFError, AttributeError):
            return False
    if suffix in (".tif", ".tiff"):
        import tifffile

        logging.getLogger("tifffile").setLevel(logging.CRITICAL)
        try:
            with tifffile.TiffFile(p) as tif:
                return bool(tif.series) and len(tif.series[0].shape) == 2
        except (tifffile.TiffFileError, ValueError, OSError, EOFError, KeyError, IndexError):
            return False
    return False


def _pixel_pair(pixel_size_nm: PixelSize | None) -> tuple[float, float] | None:
    if pixel_size_nm is None:
        return None
    values = (
        [float(pixel_size_nm)]
        if isinstance(pixel_size_nm, int | float)
        else [float(v) for v in pixel_size_nm]
    )
    if len(values) == 1:
        values = values * 2
    if len(values) != 2 or not all(math.isfinite(v) and v > 0 for v in values):
        raise ImageFileError(f"pixel_size_nm must be one or two positive numbers, got {values}")
    return values[0], values[1]


def _read_all(
    path: Path,
    *,
    pixel_size_nm: tuple[float, float] | None,
    channel: str,
    height_unit: str | None,
) -> list[AfmImage]:
    """Every frame of ``path``, with ``pixel_size_nm`` (if given) overriding the file's."""
    if not path.exists():
        raise ImageFileError(f"{path}: no such file")
    if not path.is_file():
        raise ImageFileError(f"{path}: not a file")
    suffix = path.suffix.lower()
    try:
        images = _dispatch(path, suffix, pixel_size_nm, channel, height_unit)
    except ImageFileError:
        raise
    except MemoryError:
        raise ImageFileError(f"{path}: too large to read into memory") from None
    except Exception as err:
        # A corrupt file makes third-party readers raise whatever their parsing
        # meets (struct.error, ZeroDivisionError, ...); the user gets one line
        # naming the file, never a traceback.
        raise ImageFileError(
            f"{path}: not a readable {suffix or 'image'} file ({type(err).__name__}: {err})"
        ) from None
    if pixel_size_nm is not None:
        images = [dataclasses.replace(im, pixel_size_nm=pixel_size_nm) for im in images]
    for im in images:
        check_calibration(im)
    return images


def _dispatch(
    path: Path,
    suffix: str,
    pixel_size_nm: tuple[float, float] | None,
    channel: str,
    height_unit: str | None,
) -> list[AfmImage]:
    """The reader for ``suffix``."""
    images: list[AfmImage]
    if suffix == ".npy":
        images = _read_array(path, _load_npy(path), pixel_size_nm, height_unit, "a .npy array")
    elif suffix in (".tif", ".tiff"):
        images = _read_tiff(path, pixel_size_nm, height_unit)
    elif is_nanoscope_suffix(suffix):
        images = [read_nanoscope(path, channel=channel)]
    elif suffix == ".gwy":
        images = [
            read_gwy(path, channel=channel, pixel_size_nm=pixel_size_nm, height_unit=height_unit)
        ]
    elif suffix == ".sxm":
        images = [read_sxm(path, channel=channel)]
    elif suffix == ".asd":
        images = read_asd(path, channel=channel)
    elif suffix == ".nc":
        images = read_netcdf(
            path, channel=channel, pixel_size_nm=pixel_size_nm, height_unit=height_unit
        )
    elif suffix == ".ibw":
        images = [read_ibw(path, channel=channel, pixel_size_nm=pixel_size_nm)]
    elif suffix == ".jpk":
        images = [read_jpk(path, channel=channel)]
    elif suffix == ".h5-jpk":
        images = read_h5jpk(path, channel=channel)
    elif suffix == ".stp":
        images = [read_stp(path, channel=channel)]
    else:
        known = ", ".join((*SUFFIXES, ".000-.999"))
        raise ImageFileError(f"{path}: unknown image file suffix {path.suffix!r} (known: {known})")
    return images


def load_image(
    spec: str | Path,
    *,
    pixel_size_nm: PixelSize | None = None,
    channel: str = "Height",
    height_unit: str | None = None,
) -> AfmImage:
    """Read one height image from a file.

    Parameters
    ----------
    spec : str or Path
        File path, or ``FILE:i`` for frame ``i`` of a multi-frame file.
    pixel_size_nm : float or (float, float), optional
        Pixel size (x, y) in nm. Required for files without a calibration
        (``.npy``, most ``.tif``); overrides the file's calibration otherwise.
    channel : str
        Channel to read. ``"Height"`` also selects each format's height channel
        of another name (``HeightTrace``/``HeightRetrace``, ``ZSensor``, ``Z``,
        ``Topography``, ...: :func:`afmdrift.io.pick_channel`), ``TP`` in
        ``.asd`` movies and the only (or the height/topography) field of a
        ``.gwy`` file; the image's ``channel`` says which was read.
    height_unit : str, optional
        Unit of heights stored without one (``.npy``, ``.tif``: default nm;
        unitless ``.gwy``/``.nc`` fields: required).

    Returns
    -------
    AfmImage
        Heights in nm, shape (rows, cols), float64.

    Raises
    ------
    ImageFileError
        Missing file, unknown suffix, truncated or corrupt data, unknown
        channel, a frame index out of range, or a multi-frame file without one.
    """
    path, frame = parse_spec(spec)
    images = _read_all(
        path, pixel_size_nm=_pixel_pair(pixel_size_nm), channel=channel, height_unit=height_unit
    )
    if frame is None:
        if len(images) > 1:
            raise ImageFileError(
                f"{path}: holds {len(images)} frames; choose one as {path}:i "
                f"(i = 0..{len(images) - 1})"
            )
        return images[0]
    if not 0 <= frame < len(images):
        raise ImageFileError(
            f"{path}: frame {frame} out of range "
            f"(file has {len(images)} frame(s), 0..{len(images) - 1})"
        )
    # its own heights, not a view that keeps the whole stack in memory
    chosen = images[frame]
    return dataclasses.replace(chosen, heights_nm=chosen.heights_nm.copy())


def load_stack(
    path: str | Path,
    *,
    pixel_size_nm: PixelSize | None = None,
    channel: str = "Height",
    height_unit: str | None = None,
    stream: bool = False,
) -> list[AfmImage]:
    """Read every frame of a file: an (N, rows, cols) ``.npy``/``.tif``/``.nc``
    stack, an ``.asd`` or ``.h5-jpk`` movie (a single-image file gives a list of one).

    With ``stream``, the frames of a stack of float32 or float64 heights in
    nm, stored uncompressed in one block in the machine's byte order (a
    ``.npy`` stack; a ``.tif`` stack such as ``afmdrift correct`` writes), are
    views of a read-only memory map: a caller that goes through them in turn
    holds a few frames, however long the stack, and nothing is converted. A
    frame with non-finite heights is then refused when it is measured rather
    than when the file is read. Other files are read whole.

    Parameters and errors are those of :func:`load_image`.
    """
    pixel = _pixel_pair(pixel_size_nm)
    if stream and (
        height_unit is None or length_unit_to_nm(height_unit, where="height_unit") == 1.0
    ):
        suffix = Path(path).suffix.lower()
        mapped = None
        if suffix == ".npy":
            mapped = _map_npy(Path(path), pixel)
        elif suffix in (".tif", ".tiff"):
            mapped = _map_tiff(Path(path), pixel)
        if mapped is not None:
            return mapped
    return _read_all(Path(path), pixel_size_nm=pixel, channel=channel, height_unit=height_unit)


# --------------------------------------------------------------------------- arrays


def _load_npy(path: Path) -> npt.NDArray[np.float64]:
    try:
        # Mapped first: a header that declares more data than the file holds
        # fails here, before anything is allocated.
        data = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise ImageFileError(f"{path}: not a readable .npy array ({err})") from None
    if not isinstance(data, np.ndarray) or data.dtype.kind not in "iuf":
        raise ImageFileError(f"{path}: expected a numeric array, got {getattr(data, 'dtype', '?')}")
    _check_size(path, data.shape)
    # one C-ordered copy into memory (the frames are views of it), closing the mapping
    return np.array(data, dtype=np.float64, order="C")


def _check_size(path: Path, shape: tuple[int, ...]) -> None:
    """Refuse arrays of more than :data:`MAX_VALUES` heights before reading them."""
    n = math.prod(int(v) for v in shape)
    if n > MAX_VALUES:
        raise ImageFileError(
            f"{path}: declares {n} values (shape {tuple(shape)}); the limit is {MAX_VALUES}"
        )


def _map_npy(path: Path, pixel_size_nm: tuple[float, float] | None) -> list[AfmImage] | None:
    """The frames of a ``.npy`` stack as views of a read-only memory map, or
    ``None`` when it must be read whole (another dtype or byte order, a
    single image)."""
    if not path.is_file():
        return None
    try:
        data = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise ImageFileError(f"{path}: not a readable .npy array ({err})") from None
    if not isinstance(data, np.ndarray):
        return None
    return _frame_views(path, data, pixel_size_nm, "a .npy array")


def _map_tiff(path: Path, pixel_size_nm: tuple[float, float] | None) -> list[AfmImage] | None:
    """The frames of a TIFF stack stored uncompressed in one block, as views of
    a read-only memory map (tifffile gives the block's offset), or ``None``
    when it must be read whole (compressed, in strips, another dtype)."""
    import tifffile

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.series:
                return None
            series = tif.series[0]
            offset = series.dataoffset
            dtype = np.dtype(series.dtype).newbyteorder(tif.byteorder)
            shape = tuple(int(v) for v in series.shape)
            _check_imagej_count(tif, shape, path)
            calibration = _tiff_pixel_size(tif, path)
    except (tifffile.TiffFileError, ValueError, OSError, EOFError, KeyError, IndexError) as err:
        raise ImageFileError(f"{path}: not a readable TIFF image ({err})") from None
    if offset is None or len(shape) != 3 or not dtype.isnative:
        return None
    if offset + math.prod(shape) * dtype.itemsize > path.stat().st_size:
        raise ImageFileError(f"{path}: TIFF image data end beyond the end of the file")
    data = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)
    return _frame_views(path, data, pixel_size_nm or calibration, "a TIFF image")


def _frame_views(
    path: Path,
    data: npt.NDArray[Any],
    pixel_size_nm: tuple[float, float] | None,
    what: str,
) -> list[AfmImage] | None:
    """Frames that are views of the mapped (N, rows, cols) stack ``data`` of
    float heights in nm, or ``None`` for another dtype or layout."""
    if not (
        data.ndim == 3
        and min(data.shape) > 0
        and data.dtype in (np.dtype(np.float32), np.dtype(np.float64))
        and data.flags.c_contiguous
    ):
        return None
    if pixel_size_nm is None:
        raise MissingPixelSizeError(
            f"{path}: {what} carries no pixel size; give pixel_size_nm (--pixel-size-nm)"
        )
    _check_size(path, data.shape)
    images = [
        AfmImage(heights_nm=data[i], pixel_size_nm=pixel_size_nm, path=path, frame=i,
                 channel="Height")
        for i in range(data.shape[0])
    ]  # fmt: skip
    # the pixel size once; heights are the caller's, in nm, and read frame by frame
    check_calibration(images[0], heights=False)
    return images


def _read_array(
    path: Path,
    data: npt.NDArray[np.float64],
    pixel_size_nm: tuple[float, float] | None,
    height_unit: str | None,
    what: str,
) -> list[AfmImage]:
    if data.ndim not in (2, 3) or min(data.shape) == 0:
        raise ImageFileError(
            f"{path}: {what} must be (rows, cols) or (N, rows, cols), got shape {data.shape}"
        )
    if pixel_size_nm is None:
        raise MissingPixelSizeError(
            f"{path}: {what} carries no pixel size; give pixel_size_nm (--pixel-size-nm)"
        )
    factor = length_unit_to_nm(height_unit, where="height_unit") if height_unit else 1.0
    stack = data if data.ndim == 3 else data[np.newaxis]
    if not np.all(np.isfinite(stack)):
        raise ImageFileError(f"{path}: {what} contains non-finite heights")
    # Frames are views of one float64 stack: a long stack is not held twice.
    stack = np.ascontiguousarray(stack, dtype=np.float64)
    if factor != 1.0:
        # the readers' arrays are their own: scaled in place, not copied again
        np.multiply(stack, factor, out=stack)
    return [
        AfmImage(
            heights_nm=stack[i],
            pixel_size_nm=pixel_size_nm,
            path=path,
            frame=i if data.ndim == 3 else None,
            channel="Height",
        )
        for i in range(stack.shape[0])
    ]


def _read_tiff(
    path: Path, pixel_size_nm: tuple[float, float] | None, height_unit: str | None
) -> list[AfmImage]:
    import tifffile

    # tifffile logs an ERROR for every file it finds corrupt before it raises;
    # the error reaches the user as ImageFileError, and the folder instrument
    # meets partial files routinely, so its log stays quiet.
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.series:
                raise ImageFileError(f"{path}: TIFF file holds no image")
            _check_size(path, tuple(tif.series[0].shape))
            _check_imagej_count(tif, tuple(tif.series[0].shape), path)
            data = np.asarray(tif.asarray(), dtype=np.float64)
            calibration = _tiff_pixel_size(tif, path)
            timing = _tiff_timing(tif.imagej_metadata or {}, path)
    except (tifffile.TiffFileError, ValueError, OSError, EOFError, KeyError, IndexError) as err:
        raise ImageFileError(f"{path}: not a readable TIFF image ({err})") from None
    if data.ndim == 3 and data.shape[-1] in (3, 4) and data.shape[0] > 4:
        raise ImageFileError(f"{path}: colour TIFF (shape {data.shape}) holds no height data")
    images = _read_array(path, data, pixel_size_nm or calibration, height_unit, "TIFF image")
    if data.ndim == 2 and timing:
        line_time = timing.get("line_time_s")
        images = [
            dataclasses.replace(
                images[0],
                frame_time_s=line_time * data.shape[0] if line_time is not None else None,
                **timing,
            )
        ]
    return images


def _check_imagej_count(tif: Any, shape: tuple[int, ...], path: Path) -> None:
    """Refuse an ImageJ stack holding fewer images than its description declares
    (a truncated file, which tifffile would read as its first image alone)."""
    declared = (tif.imagej_metadata or {}).get("images")
    held = math.prod(shape[:-2]) if len(shape) > 2 else 1
    if isinstance(declared, int) and declared > held:
        raise ImageFileError(
            f"{path}: ImageJ TIFF declares {declared} images but holds {held} (truncated file?)"
        )


def _tiff_timing(imagej: dict[str, Any], path: Path) -> dict[str, Any]:
    """``timestamp``, ``line_time_s``, ``scan_direction`` from ImageJ description keys."""
    out: dict[str, Any] = {}
    if "start_time" in imagej:
        try:
            out["timestamp"] = datetime.fromisoformat(str(imagej["start_time"]))
        except ValueError:
            raise ImageFileError(
                f"{path}: start_time {imagej['start_time']!r} is not ISO-8601"
            ) from None
    if "line_time_s" in imagej:
        line_time = imagej["line_time_s"]
        if not isinstance(line_time, int | float) or not 0 < line_time < math.inf:
            raise ImageFileError(f"{path}: line_time_s {line_time!r} must be a positive number")
        out["line_time_s"] = float(line_time)
    direction = str(imagej.get("scan_direction", "")).strip().lower()
    if direction in ("up", "down"):
        out["scan_direction"] = ScanDirection(direction)
    return out


def _tiff_pixel_size(tif: Any, path: Path) -> tuple[float, float] | None:
    """Pixel size from TIFF resolution tags (see the module docstring), or ``None``."""
    page = tif.pages[0]
    tags = page.tags
    if "XResolution" not in tags or "YResolution" not in tags:
        return None
    per_unit = []
    for name in ("XResolution", "YResolution"):
        num, den = tags[name].value
        if num <= 0 or den <= 0:
            return None
        per_unit.append(num / den)
    imagej = tif.imagej_metadata or {}
    unit_name = str(imagej.get("unit", "")).replace("\\u00B5", "µ")
    if unit_name:
        try:
            nm_per_unit = length_unit_to_nm(unit_name, where=f"{path}: ImageJ unit")
        except ImageFileError:
            return None
    else:
        code = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2
        nm_per_unit = {2: 2.54e7, 3: 1e7}.get(code, 0.0)
    pixel = (nm_per_unit / per_unit[0], nm_per_unit / per_unit[1])
    if not (0 < pixel[0] < _MAX_CALIBRATED_PIXEL_NM and 0 < pixel[1] < _MAX_CALIBRATED_PIXEL_NM):
        return None
    return pixel


def calibrated(
    read: Callable[[tuple[float, float] | None], T],
    pixel_size_nm: tuple[float, float] | None,
    *,
    override: bool = False,
    pixel_of: Callable[[T], tuple[float, float]],
) -> tuple[T, str | None]:
    """Read a file with the one meaning of a pixel size given by a user
    (``--pixel-size-nm``): it serves a file whose header has no calibration,
    and replaces a header's only with ``override`` (``--override-pixel-size``).

    ``read(pixel_size_nm)`` reads the file (``None``: as its header says);
    ``pixel_of`` gives the pixel size of what it read. Returns what was read,
    and a note for the user when the given size differs from the header's
    (kept, or replaced with ``override``), naming both values; else None.

    Raises
    ------
    MissingPixelSizeError
        The file has no calibration and none was given.
    """
    if pixel_size_nm is None:
        return read(None), None
    try:
        own = read(None)
    except MissingPixelSizeError:
        return read(pixel_size_nm), None
    header = pixel_of(own)
    if all(math.isclose(a, b, rel_tol=1e-6) for a, b in zip(header, pixel_size_nm, strict=True)):
        return own, None
    given = f"{pixel_size_nm[0]:g} x {pixel_size_nm[1]:g} nm"
    calibration = f"{header[0]:g} x {header[1]:g} nm"
    if override:
        note = f"pixel size {given} (--override-pixel-size) replaces the header's {calibration}"
        return read(pixel_size_nm), note
    note = (
        f"the header's pixel size {calibration} is kept; --pixel-size-nm {given} serves only "
        "files without one (--override-pixel-size replaces it)"
    )
    return own, note

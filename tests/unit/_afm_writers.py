"""Writers of vendor AFM files from their documented byte layouts, for reader tests.

Each writes the smallest file the format description allows, with known
heights and calibration; the tests then break it in chosen places.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np


def igor_wave5(
    layers: dict[str, np.ndarray],
    *,
    note: dict[str, str],
    data_units: str = "",
    byte_order: str = "<",
) -> bytes:
    """An Igor binary wave, version 5 (WaveMetrics TN003), as Asylum saves an image.

    ``layers`` maps channel labels to (lines, points) arrays in metres, row 0
    the bottom line. The wave is (points, lines, channels), stored column-major
    as float32, with the channel names as dimension-2 labels and ``note`` as
    carriage-return separated ``Key: value`` lines.
    """
    names = list(layers)
    stack = np.stack([layers[n].T for n in names], axis=2).astype(f"{byte_order}f4")
    points, lines, n = stack.shape
    data = stack.tobytes(order="F")
    note_bytes = "\r".join(f"{k}: {v}" for k, v in note.items()).encode("latin-1")
    labels = b"".join(name.encode().ljust(32, b"\0") for name in ["", *names])
    wave = bytearray(320)
    struct.pack_into(f"{byte_order}i", wave, 12, points * lines * n)  # npnts
    struct.pack_into(f"{byte_order}h", wave, 16, 2)  # NT_FP32
    struct.pack_into(f"{byte_order}h", wave, 26, 1)  # whVersion
    wave[28:33] = b"Image"
    struct.pack_into(f"{byte_order}4i", wave, 68, points, lines, n, 0)
    struct.pack_into(f"{byte_order}4d", wave, 84, 1.0, 1.0, 1.0, 1.0)
    wave[148 : 148 + len(data_units)] = data_units.encode()
    sizes = [320 + len(data), 0, len(note_bytes), 0, 0, 0, 0, 0, 0, 0, len(labels), 0, 0, 0, 0]
    header = bytearray(struct.pack(f"{byte_order}hh15i", 5, 0, *sizes))
    words = struct.unpack(f"{byte_order}192h", bytes(header) + bytes(wave))
    checksum = -sum(words) % 65536
    struct.pack_into(
        f"{byte_order}h", header, 2, checksum - 65536 if checksum > 32767 else checksum
    )
    return bytes(header) + bytes(wave) + data + note_bytes + labels


def write_ibw(path: Path, layers: dict[str, np.ndarray], **kwargs: object) -> Path:
    path.write_bytes(igor_wave5(layers, **kwargs))  # type: ignore[arg-type]
    return path


def write_jpk(
    path: Path,
    channels: dict[tuple[str, bool], np.ndarray],
    *,
    size_m: tuple[float, float],
    line_rate_hz: float,
    start: str,
    multiply: float = 1e-12,
) -> Path:
    """A JPK image scan: a big-endian TIFF with JPK's private tags (JPKImageSpec).

    Page 0 is a thumbnail with the grid and timing tags; each channel page
    holds raw int32 values with one ``nominal`` calibration slot in metres,
    value = raw × ``multiply`` + 0. ``channels`` maps (name, retrace) to
    (lines, points) arrays in metres, row 0 the bottom line.
    """
    import tifffile

    rows, cols = next(iter(channels.values())).shape
    general = [
        (0x8003, "s", 0, start, True),
        (0x8042, "d", 1, size_m[0], True),
        (0x8043, "d", 1, size_m[1], True),
        (0x8046, "i", 1, cols, True),
        (0x8047, "i", 1, rows, True),
        (0x8049, "d", 1, line_rate_hz, True),
    ]
    with tifffile.TiffWriter(path, byteorder=">") as tif:
        tif.write(np.zeros((rows, cols), np.uint8), extratags=general)
        for (name, retrace), heights_m in channels.items():
            raw = np.round(heights_m / multiply).astype(np.int32)
            tags = [
                (0x8050, "s", 0, name, True),
                (0x8051, "i", 1, int(retrace), True),
                (0x8080, "i", 1, 2, True),
                (0x8081, "s", 0, "nominal", True),
                (0x8090, "s", 0, "raw", True),
                (0x80A3, "s", 0, "NullScaling", True),
                (0x8090 + 0x30, "s", 0, "nominal", True),
                (0x80A2 + 0x30, "s", 0, "m", True),
                (0x80A3 + 0x30, "s", 0, "LinearScaling", True),
                (0x80A4 + 0x30, "d", 1, multiply, True),
                (0x80A5 + 0x30, "d", 1, 0.0, True),
            ]
            tif.write(raw, extratags=tags)
    return path


def write_h5jpk(
    path: Path,
    frames_m: np.ndarray,
    *,
    size_m: tuple[float, float],
    line_rate_hz: float,
    square: bool = True,
) -> Path:
    """A JPK ``.h5-jpk`` movie with the groups and attributes AFMReader reads:
    ``Measurement_000`` (grid, line rate) / ``Channel_000`` (``height``,
    trace) / dataset ``Height`` of shape (points × lines, frames), each
    column one frame stored row by row."""
    import h5py

    n, rows, cols = frames_m.shape
    with h5py.File(path, "w") as f:
        m = f.create_group("Measurement_000")
        m.attrs["position-pattern.grid.ulength"] = size_m[0]
        m.attrs["position-pattern.grid.vlength"] = size_m[1]
        m.attrs["position-pattern.grid.ilength"] = cols
        m.attrs["position-pattern.grid.jlength"] = rows if square else rows + 1
        m.attrs["timing-settings.scanRate"] = line_rate_hz
        c = m.create_group("Channel_000")
        c.attrs["channel.name"] = b"height"
        c.attrs["retrace"] = b"false"
        c.attrs["net-encoder.scaling.multiplier"] = 1.0
        c.attrs["net-encoder.scaling.offset"] = 0.0
        c.create_dataset("Height", data=frames_m.reshape(n, rows * cols).T)
    return path


def wsxm_stp(
    heights: np.ndarray,
    *,
    size: tuple[str, str],
    z_unit: str = "nm",
    frequency: str = "2 Hz",
    channel: str = "Topography",
) -> bytes:
    """A WSxM ``.stp`` file: the text header (sizes as ``"100 nm"``), then the
    rows as little-endian float64, top row first. ``heights`` is (rows, cols)
    in ``z_unit`` with row 0 the bottom line."""
    rows, cols = heights.shape
    body = (
        "\r\n[Control]\r\n\r\n"
        f"    X Amplitude: {size[0]}\r\n"
        f"    Y Amplitude: {size[1]}\r\n"
        f"    X-Frequency: {frequency}\r\n"
        "\r\n[General Info]\r\n\r\n"
        f"    Acquisition channel: {channel}\r\n"
        "    Image Data Type: double\r\n"
        f"    Number of columns: {cols}\r\n"
        f"    Number of rows: {rows}\r\n"
        f"    Z Amplitude: {np.ptp(heights):.6g} {z_unit}\r\n"
        "\r\n[Header end]\r\n"
    )
    head = "WSxM file copyright UAM\r\nSxM Image file\r\nImage header size: {:06d}\r\n"
    size_bytes = len(head.format(0).encode("latin-1")) + len(body.encode("latin-1"))
    text = head.format(size_bytes) + body
    return text.encode("latin-1") + np.ascontiguousarray(heights[::-1]).astype("<f8").tobytes()


def write_nc4(
    path: Path,
    heights_m: np.ndarray,
    *,
    step_m: float = 2e-9,
    variables: tuple[str, ...] = ("Height",),
) -> Path:
    """A NetCDF-4 file as netCDF4/xarray write it (afspm's files): HDF5 with
    dimension scales; each of ``variables`` holds ``heights_m`` (in m)."""
    import h5py

    rows, cols = heights_m.shape[-2:]
    with h5py.File(path, "w") as f:
        f.attrs["start_time"] = "2025-03-04T05:06:07"
        f.attrs["line_time_s"] = 0.5
        f.attrs["scan_direction"] = b"down"
        for name, n in (("y", rows), ("x", cols)):
            d = f.create_dataset(name, data=np.arange(n) * step_m)
            d.attrs["units"] = b"m"
            d.make_scale(name)
        for variable in variables:
            h = f.create_dataset(variable, data=heights_m)
            h.attrs["units"] = "m"
            h.dims[0].attach_scale(f["y"])
            h.dims[1].attach_scale(f["x"])
    return path

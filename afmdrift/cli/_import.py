"""``afmdrift import FILES... --out DIR``: build a session directory from AFM files."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from afmdrift.cli._options import add_prior_option, prior_option
from afmdrift.errors import InputError


def register(sub: Any) -> None:
    p = sub.add_parser(
        "import",
        help="Build a session directory (format v1) from AFM image files.",
        description="Read NanoScope (.spm, .000-.999), HS-AFM (.asd), Gwyddion (.gwy), "
        "NetCDF (.nc), Nanonis (.sxm), Asylum (.ibw), JPK (.jpk, .h5-jpk), WSxM (.stp), "
        ".npy and .tif files and write them as one session directory "
        "(docs/session-format.md). Frames are sorted by their header timestamps; "
        "session.json's 'source' says where each timing value came from.",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="AFM image files")
    p.add_argument("--out", required=True, metavar="DIR", help="session directory to write")
    add_file_options(p)
    p.add_argument(
        "--frame-time-s",
        type=float,
        help="scan time of one frame in s, for files whose headers give no timing",
    )
    p.add_argument(
        "--channels",
        metavar="CSV",
        help="the lab's channel log to attach (columns t_s and one per channel, t_s = 0 at "
        "the first frame's start; docs/session-format.md)",
    )
    p.add_argument(
        "--events",
        metavar="CSV",
        help="the lab's event log to attach (t_s,kind,x_nm,y_nm; any lower-case kind such as "
        "door_open or stage_move is kept)",
    )
    p.add_argument("--force", action="store_true", help="write into DIR even if it is not empty")
    add_prior_option(
        p,
        help="expected drift DX DY in px of the second frame relative to the first, stored "
        "with the session (session.json prior_px): every command that tracks the session "
        "(replay, measure, batch, diagnose, correct, evaluate) starts from it unless given "
        "its own --prior-px",
    )
    p.set_defaults(handler=_run)


def add_file_options(p: argparse.ArgumentParser) -> None:
    """``--pixel-size-nm``, ``--override-pixel-size``, ``--channel`` and
    ``--height-unit`` (shared by ``import``, ``measure`` and ``batch``)."""
    p.add_argument(
        "--pixel-size-nm",
        type=float,
        nargs="+",
        metavar="PX",
        help="pixel size in nm, PX or PX PY, for files whose header has none (.npy, "
        "plain .tif); a calibrated header is kept (a warning names both when they differ)",
    )
    p.add_argument(
        "--override-pixel-size",
        action="store_true",
        help="replace the header's calibration by --pixel-size-nm (both are printed)",
    )
    p.add_argument("--channel", default="Height", help="channel to read (default: Height)")
    p.add_argument("--height-unit", help="unit of heights stored without one (m, um, nm, pm, A)")


def pixel_size_option(
    values: list[float] | None, *, override: bool = False
) -> tuple[float, float] | None:
    """``--pixel-size-nm`` as ``(x, y)``; one value means square pixels.

    Raises
    ------
    InputError
        More than two values, or ``--override-pixel-size`` (``override``)
        without a pixel size.
    """
    if values is None:
        if override:
            raise InputError("--override-pixel-size needs --pixel-size-nm PX [PY]")
        return None
    if len(values) > 2:
        raise InputError(f"--pixel-size-nm takes PX or PX PY, got {values}")
    return (values[0], values[-1])


def _run(args: argparse.Namespace) -> int:
    from afmdrift.session import PRIOR_KEY, attach_logs, import_files, write_session

    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not args.force:
        raise InputError(f"{out}: exists and is not an empty directory (use --force to write)")
    session = import_files(
        args.files,
        pixel_size_nm=pixel_size_option(args.pixel_size_nm, override=args.override_pixel_size),
        channel=args.channel,
        height_unit=args.height_unit,
        frame_time_s=args.frame_time_s,
        override_pixel_size=args.override_pixel_size,
    )
    if args.channels is not None or args.events is not None:
        session = attach_logs(session, channels_csv=args.channels, events_csv=args.events)
    prior = prior_option(args)
    if prior is not None:
        extra = {**session.meta.extra, PRIOR_KEY: list(prior)}
        session.meta = dataclasses.replace(session.meta, extra=extra)
    write_session(session, out)
    n, rows, cols = session.frames.shape
    px, py = session.meta.pixel_size_nm
    span = float(session.frame_times[-1, 1] - session.frame_times[0, 0])
    print(
        f"{out}: {n} frame(s) of {rows}x{cols} px at {px:g} x {py:g} nm/px "
        f"over {span:g} s, line time {session.meta.line_time_s:g} s"
    )
    return 0

"""``afmdrift correct SESSION --out DIR``: frames de-warped by the drift trajectory."""

from __future__ import annotations

import argparse
from typing import Any

from afmdrift.cli._options import (
    add_prior_option,
    add_registration_options,
    prior_option,
    registration_options,
)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "correct",
        help="Write the frames of a session with each row moved back by the drift at its "
        "scan time.",
        description="Run SESSION (format v1) through the daemon's pipeline and de-warp "
        "every measured frame with the drift trajectory, on both axes and across frames, "
        "into the geometry of the session reference (docs/service.md).",
    )
    p.add_argument("session", help="session directory (format v1)")
    p.add_argument("--out", required=True, help="directory to write")
    p.add_argument(
        "--format",
        choices=("session", "npy"),
        default="session",
        help="a session directory (default) or DIR/frames.npy with DIR/frames.csv",
    )
    p.add_argument(
        "--trajectory",
        choices=("smoothed", "causal"),
        default="smoothed",
        help="the whole session at once (default), or what the daemon knew at each frame",
    )
    p.add_argument(
        "--fill",
        choices=("nearest", "nan"),
        default="nearest",
        help="content a frame did not scan: the nearest scanned value (default) or NaN",
    )
    p.add_argument(
        "--config", default=None, help="TOML configuration (default: config/default.toml)"
    )
    add_prior_option(p)
    add_registration_options(p)
    p.set_defaults(handler=_correct)


def _correct(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.runs import correct_session
    from afmdrift.session import read_session

    config = registration_options(args, load_config(args.config))
    summary = correct_session(
        read_session(args.session),
        args.out,
        config=config,
        mode=args.trajectory,
        output=args.format,
        fill=args.fill,
        prior_px=prior_option(args),
    )
    skipped = ", ".join(map(str, summary.frames_skipped)) or "none"
    print(
        f"{summary.frames_written} frames de-warped ({summary.mode} trajectory) into "
        f"{summary.out}; not measured, skipped: {skipped}"
    )
    return 0

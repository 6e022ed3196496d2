"""``afmdrift replay SESSION --out RUN_DIR``: the daemon's pipeline over a recorded session."""

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
        "replay",
        help="Run the daemon's pipeline over a recorded session, as fast as possible.",
        description="Feed every frame of SESSION (format v1) with its channels and events "
        "through the same per-frame code as `afmdrift run`; write the run store and "
        "RUN_DIR/measurements.csv (columns in docs/service.md). Exit status 1 when fewer "
        "than 2 frames have a valid measurement (no prediction error; the run is still "
        "written), 2 on an error.",
    )
    p.add_argument("session", help="session directory (format v1)")
    p.add_argument("--out", required=True, help="run directory to write (must be empty)")
    p.add_argument(
        "--config", default=None, help="TOML configuration (default: config/default.toml)"
    )
    add_prior_option(p)
    add_registration_options(p)
    p.set_defaults(handler=_replay)


def _replay(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.errors import TooFewFramesError
    from afmdrift.runs import MIN_REPLAY_FRAMES, replay_session

    config = registration_options(args, load_config(args.config))
    summary = replay_session(args.session, args.out, config=config, prior_px=prior_option(args))
    line = (
        f"{summary.frames} frames replayed in {summary.wall_s:.1f} s "
        f"({summary.fed_model} fed the model)"
    )
    enough = summary.valid_frames >= MIN_REPLAY_FRAMES
    if enough:
        line += (
            f"; prediction error mean {summary.mean_pred_error_nm:.2f} nm, "
            f"max {summary.max_pred_error_nm:.2f} nm"
        )
    print(line)
    print(f"run directory: {summary.run_dir}  measurements: {summary.measurements_csv}")
    if not enough:
        # the run is written (its frames are recorded); there is no error to give
        raise TooFewFramesError(
            summary.valid_frames,
            MIN_REPLAY_FRAMES,
            str(args.session),
            "a prediction error needs a frame predicted from an earlier one",
        )
    return 0

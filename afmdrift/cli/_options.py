"""Options that several commands share, defined once."""

from __future__ import annotations

import argparse
from typing import Any

#: What ``--prior-px`` means for a command that tracks a recording.
PRIOR_HELP = (
    "expected drift DX DY in px of the first frame after the first: it centres that "
    "frame's block search and, on a periodic sample, picks the lattice translation "
    "nearest it (the result then says decided_by: prior); later frames take the "
    "tracker's prediction. Default: the one 'afmdrift import --prior-px' stored with "
    "a session, else none"
)


def add_prior_option(p: Any, *, help: str = PRIOR_HELP) -> None:
    """``--prior-px DX DY`` on parser ``p``."""
    p.add_argument("--prior-px", type=float, nargs=2, metavar=("DX", "DY"), help=help)


def prior_option(args: argparse.Namespace) -> tuple[float, float] | None:
    """The ``--prior-px`` given (validated: two finite numbers), or None.

    Raises
    ------
    ConfigError
        Not finite; the message names the option and the value.
    """
    import math

    from afmdrift.errors import ConfigError

    given = getattr(args, "prior_px", None)
    if given is None:
        return None
    dx, dy = float(given[0]), float(given[1])
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise ConfigError(f"--prior-px must be two finite numbers (px), got {dx} {dy}")
    return dx, dy

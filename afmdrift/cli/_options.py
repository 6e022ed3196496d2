"""Options that several commands share, defined once."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from afmdrift.config import AfmdriftConfig, RegistrationConfig

#: A whole configuration or its ``[registration]`` section.
Config = TypeVar("Config", "AfmdriftConfig", "RegistrationConfig")

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


def add_registration_options(p: Any) -> None:
    """``--max-shift-px B`` and ``--lattice {track,equivalent}`` on parser ``p``:
    what every command that registers frames may be told (they override
    ``[registration] max_shift_px`` and ``lattice``)."""
    p.add_argument(
        "--max-shift-px",
        type=float,
        metavar="B",
        help="the largest drift possible between a frame and the reference it is "
        "registered on, px per axis: lattice translations beyond it are excluded (on a "
        "periodic sample a bound under half a period decides; decided_by: bound) and a "
        "result beyond it is refused (overrides [registration] max_shift_px)",
    )
    p.add_argument(
        "--lattice",
        choices=("track", "equivalent"),
        help="on a periodic sample whose lattice translations the frames cannot tell "
        "apart: track (default: the prior or --max-shift-px decides, else refuse) or "
        "equivalent (register the frames: take the translation nearest the prior or zero, "
        "decided_by: equivalent; any lattice-equivalent shift registers them as well, but "
        "it is not the drift)",
    )


def registration_options(args: argparse.Namespace, config: Config) -> Config:
    """``config`` (an :class:`~afmdrift.config.AfmdriftConfig`, or a
    :class:`~afmdrift.config.RegistrationConfig`) with ``--max-shift-px`` and
    ``--lattice`` applied, validated.

    Raises
    ------
    ConfigError
        A value out of range; the message names the option.
    """
    from pydantic import ValidationError

    from afmdrift.config import AfmdriftConfig, RegistrationConfig, describe_validation_error
    from afmdrift.errors import ConfigError

    overrides = {
        key: value
        for key, value in (
            ("max_shift_px", getattr(args, "max_shift_px", None)),
            ("lattice", getattr(args, "lattice", None)),
        )
        if value is not None
    }
    if not overrides:
        return config
    registration = config.registration if isinstance(config, AfmdriftConfig) else config
    try:
        updated = RegistrationConfig.model_validate({**registration.model_dump(), **overrides})
    except ValidationError as err:
        raise ConfigError(
            describe_validation_error(
                err, source="--max-shift-px/--lattice", root=RegistrationConfig
            )
        ) from None
    if isinstance(config, AfmdriftConfig):
        return config.model_copy(update={"registration": updated})
    return updated

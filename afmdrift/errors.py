"""Exception hierarchy shared by every part of afmdrift.

Every error that afmdrift raises on purpose derives from :class:`AfmdriftError`,
so the command line can print its message (which always names the offending
item) instead of a traceback. Errors about bad values also derive from
:class:`ValueError`, so numerical code reads naturally to NumPy users.
:class:`TooFewFramesError` is an :class:`InputError` the command line tells
apart by its type (exit status 1: the input is readable but too short for
the result asked of it).
"""

from __future__ import annotations

__all__ = ["AfmdriftError", "ConfigError", "InputError", "TooFewFramesError"]


class AfmdriftError(Exception):
    """Base class of all deliberate afmdrift errors."""


class ConfigError(AfmdriftError, ValueError):
    """A configuration file or value is invalid; the message names the key."""


class InputError(AfmdriftError, ValueError):
    """An input file, array or session is unusable; the message names the item."""


class TooFewFramesError(InputError):
    """A recording has too few frames with a valid measurement for the result asked.

    Parameters
    ----------
    valid : int
        Frames with a valid measurement (those the result would use).
    needed : int
        The least number of them the result needs.
    where : str
        The recording (or what was read), named first in the message.
    why : str
        What needs ``needed`` frames, given in parentheses.
    """

    def __init__(self, valid: int, needed: int, where: str = "", why: str = "") -> None:
        self.valid = valid
        self.needed = needed
        self.where = where
        self.why = why
        text = f"too few frames: {valid} valid, {needed} needed"
        if where:
            text = f"{where}: {text}"
        if why:
            text = f"{text} ({why})"
        super().__init__(text)

    def __reduce__(self) -> tuple[type[TooFewFramesError], tuple[int, int, str, str]]:
        # pickled (to or from a Dask worker) by its fields, not its message
        return type(self), (self.valid, self.needed, self.where, self.why)

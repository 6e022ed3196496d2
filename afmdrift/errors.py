"""Exception hierarchy shared by every part of afmdrift.

Every error that afmdrift raises on purpose derives from :class:`AfmdriftError`,
so the command line can print its message (which always names the offending
item) instead of a traceback. Errors about bad values also derive from
:class:`ValueError`, so numerical code reads naturally to NumPy users.
"""

from __future__ import annotations

__all__ = ["AfmdriftError", "ConfigError", "InputError"]


class AfmdriftError(Exception):
    """Base class of all deliberate afmdrift errors."""


class ConfigError(AfmdriftError, ValueError):
    """A configuration file or value is invalid; the message names the key."""


class InputError(AfmdriftError, ValueError):
    """An input file, array or session is unusable; the message names the item."""

"""Typed errors of the registration engine."""

from __future__ import annotations

from afmdrift.errors import InputError

__all__ = ["InvalidFrameError", "RegistrationError"]


class RegistrationError(InputError):
    """Two frames cannot be registered: shapes or pixel sizes disagree, or an
    argument is out of range. The message names the item and its value."""


class InvalidFrameError(RegistrationError):
    """One image is unusable: not 2-D, too small, NaN/Inf pixels, or no texture."""


class NearlyBlankError(InvalidFrameError):
    """A frame has almost no texture (few non-zero gradient pixels); it is
    measured only when the whole-image alignment locks onto it strongly
    (:func:`afmdrift.registration._checks.allow_nearly_blank`)."""

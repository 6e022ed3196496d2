"""Which channel of a file holds the heights, in every format's own names.

The default channel is ``Height``. Instruments name their height channel
differently: NanoScope ``Height``, Asylum ``HeightTrace``/``HeightRetrace`` and
``ZSensor``, afspm's NetCDF-4 files ``HeightRetrace``, Nanonis ``Z``, WSxM and
others ``Topography``, JPK ``height_trace``. :func:`pick_channel` finds the
one asked for by name (exactly, then ignoring case, spaces, ``_`` and
``-``) and, for the default ``Height``, the first height channel of
:data:`HEIGHT_FAMILIES` × :data:`DIRECTIONS` present in the file. The image
read says which channel it is (``AfmImage.channel``), and ``afmdrift
measure`` reports it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from afmdrift.io._image import ImageFileError

__all__ = ["DEFAULT_CHANNEL", "DIRECTIONS", "HEIGHT_FAMILIES", "pick_channel"]

#: The channel every reader is asked for unless the user names another.
DEFAULT_CHANNEL = "Height"
#: Names of height channels, most direct measure of the height first
#: (normalised: lower case, no spaces, ``_`` or ``-``).
HEIGHT_FAMILIES: tuple[str, ...] = ("height", "topography", "topo", "zsensor", "z")
#: Scan directions, trace (forward) before retrace (backward).
DIRECTIONS: tuple[str, ...] = ("", "trace", "forward", "fwd", "retrace", "backward", "bwd")


def _norm(name: str) -> str:
    return re.sub(r"[\s_\-]+", "", name).lower()


def pick_channel(names: Sequence[str], channel: str, *, where: str, what: str = "channel") -> str:
    """The name in ``names`` that ``channel`` selects.

    Parameters
    ----------
    names : sequence of str
        The file's channel (or variable) names.
    channel : str
        The name asked for; :data:`DEFAULT_CHANNEL` also selects any height
        channel (the first of :data:`HEIGHT_FAMILIES` × :data:`DIRECTIONS`).
    where : str
        The file, for the error message.
    what : str
        What the file calls its channels (``variable`` in NetCDF).

    Raises
    ------
    ImageFileError
        No such channel; the message lists the file's names.
    """
    if channel in names:
        return channel
    normal: dict[str, str] = {}
    for name in names:
        normal.setdefault(_norm(name), name)
    hit = normal.get(_norm(channel))
    if hit is not None:
        return hit
    if _norm(channel) == _norm(DEFAULT_CHANNEL):
        for family in HEIGHT_FAMILIES:
            for direction in DIRECTIONS:
                hit = normal.get(family + direction)
                if hit is not None:
                    return hit
    raise ImageFileError(f"{where}: no {what} {channel!r} (has: {', '.join(names) or 'none'})")

"""The Nanonis (SPECS) controller: TCP codec and async driver.

``nanonis://HOST:PORT`` in ``[driver] transport`` selects :class:`NanonisDriver`;
the protocol and what the driver can and cannot do are in ``docs/protocol.md``
and ``docs/instruments.md``.
"""

from afmdrift.drivers.nanonis._codec import COMMANDS, NanonisError
from afmdrift.drivers.nanonis._driver import (
    NANONIS_SCHEME,
    DriftCompState,
    NanonisDriver,
    nanonis_socket_url,
)

__all__ = [
    "COMMANDS",
    "NANONIS_SCHEME",
    "DriftCompState",
    "NanonisDriver",
    "NanonisError",
    "nanonis_socket_url",
]

"""afmdrift: keep an AFM on the same nanometre spot while the instrument drifts.

Data flow: ``drivers`` (instrument or replay) → ``registration`` (block phase
correlation) → ``model`` (prediction) → reconstruction of d(t) → ``service``
(ZeroMQ publisher and run store). See ``docs/architecture.md``.
"""

from afmdrift._version import __version__
from afmdrift.errors import AfmdriftError, ConfigError, InputError

__all__ = ["AfmdriftError", "ConfigError", "InputError", "__version__"]

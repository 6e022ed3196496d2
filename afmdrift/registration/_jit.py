"""How the registration kernels are compiled (Numba): three flavours of
``njit``, all without the GIL, cached on disk, without bounds checks and with
NumPy's error model (a division by zero gives inf or NaN, as in NumPy).

Numba keys a cached kernel on its own module's source only (Numba issue
#1833): a kernel that calls, and so inlines, a kernel of another module would
keep the old machine code after that module changed. The kernels live in
several modules (:data:`KERNEL_MODULES`) and call each other across them, so
every kernel's cache is stamped with the sources of all of them: a change to
any kernel module recompiles them all.

The caches sit beside the modules (``__pycache__``) or under
``$NUMBA_CACHE_DIR``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba

__all__ = ["KERNEL_MODULES", "jit", "jit_finite", "jit_sums"]

#: The modules of this package that define compiled kernels.
KERNEL_MODULES = (
    "_intrinsics",
    "_jit",
    "_passes",
    "_peaks",
    "_selection",
    "_spectra",
    "_subpixel",
)


def _sources_digest() -> bytes | None:
    """SHA-256 of the kernel modules' sources, or None where they cannot be
    read (then each kernel keeps Numba's own stamp)."""
    here = Path(__file__).parent
    digest = hashlib.sha256()
    try:
        for name in KERNEL_MODULES:
            digest.update((here / f"{name}.py").read_bytes())
    except OSError:
        return None
    return digest.digest()


_SOURCES = _sources_digest()


def _compiler(**flags: Any) -> Callable[[Any], Any]:
    compile_ = numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, **flags)

    def decorate(fn: Any) -> Any:
        dispatcher = compile_(fn)
        # Numba's cache index holds the stamp it was written with and is
        # discarded when the stamp differs (numba.core.caching); an index
        # without one (another Numba) is left as it is.
        index: Any = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
        stamp = getattr(index, "_source_stamp", None)
        if stamp is not None and _SOURCES is not None:
            index._source_stamp = (stamp, _SOURCES)
        return dispatcher

    return decorate


#: The default: IEEE arithmetic, no reassociation (results as written).
jit = _compiler()
#: For loops over finite values only (maxima): all fastmath flags, which drop
#: the NaN handling of the comparisons (the float maxima still stay scalar
#: loops, about one element per cycle, measured).
jit_finite = _compiler(fastmath=True)
#: For sums (the sub-pixel step, the gradient pass's counts): reassociation
#: (vectorised sums, last bits depending on the compiled order) but no
#: assumption of finite values.
jit_sums = _compiler(fastmath={"reassoc", "contract", "nsz", "arcp"})

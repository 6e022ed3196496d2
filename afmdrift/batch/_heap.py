"""The C heap of a Dask worker while it runs a job: freed frame-sized arrays
are kept for the next frame instead of going back to the kernel.

A Dask nanny starts its worker with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``), so that the worker's memory
returns to the system quickly. Setting that variable also switches off glibc's
dynamic mmap threshold (mallopt(3): "dynamic adjustment of the mmap threshold
is disabled if any of M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD or
M_MMAP_MAX is set"). Every array of 128 KiB or more, which is every frame-sized
array of the pipeline, is then its own ``mmap``: the kernel maps, zero-fills
and unmaps its pages for each frame. That cost the pipeline 20-30 % of its
time on one worker, and more with two workers side by side (their page
faults contend); see ``benchmarks/RESULTS.md``.

:func:`job_heap` raises the two thresholds for the length of a job, so that
the frames' arrays come from the heap and are reused, and on leaving puts back
the thresholds the process was started with and returns the free heap to the
system (``malloc_trim``). It acts only in a process started with
``MALLOC_TRIM_THRESHOLD_``, whose thresholds are fixed already: in any other
process (``afmdrift measure``, a worker without a nanny, a test) glibc's
dynamic threshold is left on, as setting a threshold would switch it off for
the rest of the process. Outside glibc (macOS, Windows, musl) it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import logging
import os
import sys
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["JOB_MMAP_THRESHOLD", "JOB_TRIM_THRESHOLD", "job_heap"]

log = logging.getLogger(__name__)

#: mallopt(3) parameters, from glibc's ``malloc.h``.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's defaults for both thresholds (128 KiB).
_GLIBC_DEFAULT = 128 * 1024
#: During a job, arrays under 32 MiB (glibc's largest mmap threshold on 64-bit
#: systems; a 2048² float64 frame) come from the heap.
JOB_MMAP_THRESHOLD = 32 * 2**20
#: During a job, up to 64 MiB of free memory at the heap's top is kept for the
#: next frame rather than returned to the kernel after each.
JOB_TRIM_THRESHOLD = 64 * 2**20

_lock = threading.Lock()
_active = 0


@functools.cache
def _libc() -> Any | None:
    """glibc's functions, or None where the C library is not glibc (looked up
    once per process)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt, trim = libc.mallopt, libc.malloc_trim
    except (OSError, AttributeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return libc


def _started_with() -> tuple[int, int] | None:
    """The (mmap, trim) thresholds the process was started with, when its
    environment fixed them (``MALLOC_TRIM_THRESHOLD_``, as a Dask nanny sets);
    None when glibc's dynamic threshold is on."""
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    if trim is None:
        return None
    try:
        mmap = int(os.environ.get("MALLOC_MMAP_THRESHOLD_", str(_GLIBC_DEFAULT)))
        return max(mmap, 0), max(int(trim), 0)
    except ValueError:  # glibc ignores a value it cannot read: not ours to guess
        return None


@contextlib.contextmanager
def job_heap() -> Iterator[None]:
    """Keep frame-sized arrays in the heap while the ``with`` block runs, in a
    process started with ``MALLOC_TRIM_THRESHOLD_`` (see the module
    docstring). Jobs that overlap on a worker with several threads share one
    setting: the first to enter sets it, the last to leave puts the worker's
    back."""
    global _active
    libc, started = _libc(), _started_with()
    if libc is None or started is None:
        yield
        return
    with _lock:
        _active += 1
        if _active == 1 and not (
            libc.mallopt(_M_MMAP_THRESHOLD, JOB_MMAP_THRESHOLD)
            and libc.mallopt(_M_TRIM_THRESHOLD, JOB_TRIM_THRESHOLD)
        ):
            log.debug("mallopt refused the job's heap thresholds; the worker's stay")
    try:
        yield
    finally:
        with _lock:
            _active -= 1
            if _active == 0:
                libc.mallopt(_M_MMAP_THRESHOLD, started[0])
                libc.mallopt(_M_TRIM_THRESHOLD, started[1])
                libc.malloc_trim(0)

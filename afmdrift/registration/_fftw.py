"""FFTW plans and wisdom for the batched block transforms.

Plans are built once per block-stack shape by :class:`BatchedRealFFT` and kept
with their aligned input and output arrays. They are made and executed
through FFTW's C interface (``fftwf_plan_many_dft_r2c``, ``fftwf_plan_guru_*``
and the new-array execute functions ``fftwf_execute_dft_*``; FFTW manual,
"New-array Execute Functions") of the single-precision library pyFFTW uses
(see :func:`fftwf`), so that compiled code can run them without the GIL (see
:func:`afmdrift.registration._passes.measure_batches`); pyFFTW provides the
library, aligned arrays and the wisdom in memory. FFTW *wisdom* (the planner's
measurements) is loaded once per process from a file and written back after
new plans were made, so the second run of afmdrift plans in milliseconds.

The wisdom file is, in order of precedence, the ``fftw_wisdom`` setting of
:class:`~afmdrift.registration.RegistrationConfig`, the environment variable
``AFMDRIFT_FFTW_WISDOM``, or ``$XDG_CACHE_HOME/afmdrift/fftw-wisdom-<pyfftw
version>`` (``~/.cache`` when ``XDG_CACHE_HOME`` is unset). An empty string
disables wisdom. A missing, corrupt or unwritable file only logs a message.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import tempfile
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import pyfftw

from afmdrift.registration._spectra import STRIP_CHUNK

__all__ = ["BatchedRealFFT", "Fftwf", "default_wisdom_path", "fftwf", "resolve_wisdom_path"]

_log = logging.getLogger(__name__)

_MAGIC = b"afmdrift-fftw-wisdom 1\n"
# Reentrant: a plan finalizer (_destroy) may run from garbage collection
# while this thread plans.
_lock = threading.RLock()
_loaded: set[Path] = set()

Planner = Literal["estimate", "measure", "patient"]
# Planner flags of fftw3.h.
_FLAGS: dict[str, int] = {"estimate": 1 << 6, "measure": 0, "patient": 1 << 5}
_DESTROY_INPUT = 1
_FORWARD = -1
_BACKWARD = 1


def default_wisdom_path() -> Path:
    """``$XDG_CACHE_HOME/afmdrift/fftw-wisdom-<pyfftw version>``."""
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "afmdrift" / f"fftw-wisdom-{pyfftw.__version__}"


def resolve_wisdom_path(setting: str | None) -> Path | None:
    """The wisdom file to use, or None when wisdom is disabled (empty string)."""
    if setting is None:
        setting = os.environ.get("AFMDRIFT_FFTW_WISDOM")
    if setting is None:
        return default_wisdom_path()
    if setting == "":
        return None
    return Path(setting).expanduser()


def _load_wisdom(path: Path) -> None:
    if path in _loaded:
        return
    _loaded.add(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return
    except OSError as err:
        _log.warning("cannot read FFTW wisdom %s: %s", path, err.strerror)
        return
    parts = _decode(data)
    if parts is None:
        _log.warning("ignoring malformed FFTW wisdom file %s", path)
        return
    pyfftw.import_wisdom(parts)


def _decode(data: bytes) -> tuple[bytes, bytes, bytes] | None:
    if not data.startswith(_MAGIC):
        return None
    rest = data[len(_MAGIC) :]
    parts: list[bytes] = []
    for _ in range(3):
        head, sep, rest = rest.partition(b"\n")
        if not sep or not head.isdigit() or len(rest) < int(head):
            return None
        parts.append(rest[: int(head)])
        rest = rest[int(head) :]
    return parts[0], parts[1], parts[2]


def _save_wisdom(path: Path) -> None:
    body = b"".join(b"%d\n%b" % (len(p), p) for p in pyfftw.export_wisdom())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".fftw-wisdom-")
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(_MAGIC + body)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as err:
        _log.info("cannot write FFTW wisdom %s: %s", path, err.strerror or err)


class _IODim(ctypes.Structure):
    """``fftwf_iodim``: length, input stride and output stride (elements)."""

    _fields_ = [("n", ctypes.c_int), ("is_", ctypes.c_int), ("os", ctypes.c_int)]


def _dims(*dims: tuple[int, int, int]) -> ctypes.Array[_IODim]:
    return (_IODim * len(dims))(*(_IODim(*d) for d in dims))


@dataclass(frozen=True)
class Fftwf:
    """The single-precision FFTW library pyFFTW uses (see :func:`fftwf`).

    ``execute_*`` are the addresses of FFTW's new-array execute functions
    (``fftwf_execute_dft_r2c``, ``fftwf_execute_dft``,
    ``fftwf_execute_dft_c2r``, each ``(plan, in, out)``), for compiled code
    that calls them without the GIL."""

    lib: ctypes.CDLL
    #: Where ``fftwf_plan_with_nthreads`` is, if FFTW has threads.
    threads: ctypes.CDLL | None
    execute_r2c: int
    execute_c2c: int
    execute_c2r: int


@functools.cache
def fftwf() -> Fftwf:
    """The single-precision FFTW library pyFFTW uses (loaded once).

    Its functions are looked up through pyFFTW's own extension module: the
    dynamic linker searches that module's dependencies, so these are the
    functions of the very library (and threads library) pyFFTW loaded, and
    its plans, wisdom and ours are one library's. The planner is made
    thread-safe (``fftwf_make_planner_thread_safe``), so that afmdrift's
    planning and any pyFFTW use in another thread cannot meet in it."""
    lib = ctypes.CDLL(pyfftw.pyfftw.__file__)
    p, i, u = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint
    dims = ctypes.POINTER(_IODim)
    ints = ctypes.POINTER(ctypes.c_int)
    many = [i, ints, i, p, p, i, i, p, p, i, i, u]
    try:
        for name, restype, argtypes in (
            ("fftwf_plan_many_dft_r2c", p, many),
            ("fftwf_plan_guru_dft", p, [i, dims, i, dims, p, p, i, u]),
            ("fftwf_plan_guru_dft_c2r", p, [i, dims, i, dims, p, p, u]),
            ("fftwf_execute_dft_r2c", None, [p, p, p]),
            ("fftwf_execute_dft", None, [p, p, p]),
            ("fftwf_execute_dft_c2r", None, [p, p, p]),
            ("fftwf_destroy_plan", None, [p]),
        ):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
    except AttributeError as err:
        raise ImportError(f"pyFFTW's FFTW library lacks a function afmdrift needs: {err}") from None
    threads: ctypes.CDLL | None = lib
    try:
        lib.fftwf_init_threads.restype = i
        lib.fftwf_plan_with_nthreads.argtypes = [i]
        lib.fftwf_plan_with_nthreads.restype = None
        lib.fftwf_make_planner_thread_safe.restype = None
    except AttributeError:
        threads = None  # an FFTW built without threads: one thread per plan
    if threads is not None:
        lib.fftwf_init_threads()
        lib.fftwf_make_planner_thread_safe()

    def address(fn: ctypes._CFuncPtr) -> int:  # type: ignore[name-defined]
        value = ctypes.cast(fn, ctypes.c_void_p).value
        assert value is not None
        return value

    return Fftwf(
        lib=lib,
        threads=threads,
        execute_r2c=address(lib.fftwf_execute_dft_r2c),
        execute_c2c=address(lib.fftwf_execute_dft),
        execute_c2r=address(lib.fftwf_execute_dft_c2r),
    )


def _destroy(lib: ctypes.CDLL, plans: tuple[int, ...]) -> None:
    with _lock:  # FFTW's planner and plan destruction are not thread-safe
        for plan in plans:
            lib.fftwf_destroy_plan(plan)


class BatchedRealFFT:
    """Forward and inverse 2-D real FFTs over a stack of equal blocks.

    Parameters
    ----------
    n_blocks : int
        Batch size.
    block_shape : (int, int)
        ``(rows, cols)`` of each block.
    threads : int
        FFTW threads (more than one needs FFTW's threads library).
    planner : {"estimate", "measure", "patient"}
        FFTW planner effort.
    wisdom_path : Path or None
        Wisdom file to load before and update after planning.
    share : BatchedRealFFT, optional
        Plan on the first ``n_blocks`` blocks of its arrays instead of new
        ones (plans for several batch sizes on one set of work arrays).
    out_rows : int, optional
        Rows of the inverse transform's output that are needed, from the
        first (default: all). The inverse is a column transform over the
        whole spectrum followed by row transforms of only the first
        ``out_rows`` rows (with half the rows, about 30 % less work than the
        full 2-D inverse).
    strip_rows : int, optional
        Also make the arrays and plans of a forward transform in two steps
        (:func:`afmdrift.registration._spectra.forward_strips`): row
        transforms of up to ``strip_rows`` windowed image rows,
        :data:`STRIP_CHUNK` rows per call, and the column transforms of
        ``spectrum`` in place.

    Attributes
    ----------
    real : ndarray, shape (n_blocks, rows, cols), float32
        Aligned input of :meth:`forward`.
    spectrum : ndarray, shape (n_blocks, rows, cols // 2 + 1), complex64
        Aligned output of :meth:`forward` and input of :meth:`inverse`
        (overwritten by the inverse transform): the caller turns the spectra
        into what is to be transformed back in place, so that one batch's
        arrays stay small enough for the core's cache.
    out : ndarray, shape (n_blocks, out_rows, cols), float32
        Output of :meth:`inverse` (``real`` itself when all rows are
        needed).
    strip : ndarray, shape (strip_rows + STRIP_CHUNK, cols), float32
        Rows to transform (none without ``strip_rows``).
    strip_spectrum : ndarray, shape (strip_rows + STRIP_CHUNK, cols // 2 + 1), complex64
        Their transforms.
    plans : ndarray, shape (3,) or (5,), uint64
        The FFTW plans: forward, inverse over columns (in place), inverse
        over the first ``out_rows`` rows; with ``strip_rows``, also the
        forward transform over the columns of ``spectrum`` (in place) and the
        row transform of :data:`STRIP_CHUNK` rows from ``strip`` to
        ``strip_spectrum``.
    pointers : ndarray, shape (3,) or (5,), uint64
        Addresses of ``real``, ``spectrum``, ``out`` (and ``strip``,
        ``strip_spectrum``): with ``plans`` and :class:`Fftwf`'s execute
        functions, what compiled code needs to run the transforms itself.
    """

    real: npt.NDArray[np.float32]
    spectrum: npt.NDArray[np.complex64]
    out: npt.NDArray[np.float32]
    strip: npt.NDArray[np.float32]
    strip_spectrum: npt.NDArray[np.complex64]

    def __init__(
        self,
        n_blocks: int,
        block_shape: tuple[int, int],
        *,
        threads: int = 1,
        planner: Planner = "measure",
        wisdom_path: Path | None = None,
        out_rows: int | None = None,
        share: BatchedRealFFT | None = None,
        strip_rows: int | None = None,
    ) -> None:
        rows, cols = block_shape
        keep = rows if out_rows is None else min(out_rows, rows)
        self._arrays(n_blocks, (rows, cols), keep, share, strip_rows)
        lib = fftwf()
        self._lib = lib.lib
        if threads > 1 and lib.threads is None:
            raise ValueError("FFTW's threads library was not found: use threads=1")
        real, spec, out, strip, strip_spec = self._addresses()
        with _lock:
            if wisdom_path is not None:
                _load_wisdom(wisdom_path)
            before = pyfftw.export_wisdom()
            if lib.threads is not None:
                lib.threads.fftwf_plan_with_nthreads(threads)
            try:
                plans = self._plan(
                    n_blocks, (rows, cols), keep, _FLAGS[planner] | _DESTROY_INPUT,
                    stripped=strip_rows is not None,
                )  # fmt: skip
            finally:
                if lib.threads is not None:
                    lib.threads.fftwf_plan_with_nthreads(1)
            made = tuple(int(q) for q in plans if q)
            weakref.finalize(self, _destroy, self._lib, made)
            if len(made) < len(plans):
                raise RuntimeError(f"FFTW could not plan {n_blocks} blocks of {rows}×{cols}")
            if wisdom_path is not None and pyfftw.export_wisdom() != before:
                _save_wisdom(wisdom_path)
        self.plans = np.array(made, dtype=np.uint64)
        self.pointers = np.array([real, spec, out, strip, strip_spec][: len(made)], dtype=np.uint64)
        # the execute calls' arguments, as ctypes pointers made once
        ptr = ctypes.c_void_p
        self._forward_args = (ptr(made[0]), ptr(real), ptr(spec))
        self._inverse_args = (
            (ptr(made[1]), ptr(spec), ptr(spec)),
            (ptr(made[2]), ptr(spec), ptr(out)),
        )
        self.real.fill(0.0)
        self.out.fill(0.0)

    def _arrays(
        self,
        n_blocks: int,
        block_shape: tuple[int, int],
        keep: int,
        share: BatchedRealFFT | None,
        strip_rows: int | None,
    ) -> None:
        """The aligned arrays (see the class's attributes): new ones, or the
        first ``n_blocks`` blocks of ``share``'s."""
        rows, cols = block_shape
        half = cols // 2 + 1
        stripped = strip_rows is not None
        if share is not None:
            if (
                share.real.shape[0] < n_blocks
                or share.real.shape[1:] != (rows, cols)
                or share.out.shape[1:] != (keep, cols)
                or (stripped and share.strip.shape[0] < strip_rows + STRIP_CHUNK)  # type: ignore[operator]
            ):
                raise ValueError("a shared BatchedRealFFT needs as many blocks and the same shape")
            self.real = share.real[:n_blocks]
            self.spectrum = share.spectrum[:n_blocks]
            self.out = share.out[:n_blocks]
            self.strip, self.strip_spectrum = share.strip, share.strip_spectrum
            return
        self.real = pyfftw.empty_aligned((n_blocks, rows, cols), dtype="float32")
        self.spectrum = pyfftw.empty_aligned((n_blocks, rows, half), "complex64")
        self.out = (
            pyfftw.empty_aligned((n_blocks, keep, cols), dtype="float32")
            if keep < rows
            else self.real
        )
        strips = strip_rows + STRIP_CHUNK if strip_rows is not None else 0
        self.strip = pyfftw.empty_aligned((strips, cols), dtype="float32")
        self.strip_spectrum = pyfftw.empty_aligned((strips, half), "complex64")
        self.strip.fill(0.0)

    def _addresses(self) -> tuple[int, ...]:
        """Addresses of ``real``, ``spectrum``, ``out``, ``strip`` and
        ``strip_spectrum``."""
        arrays = (self.real, self.spectrum, self.out, self.strip, self.strip_spectrum)
        return tuple(int(a.ctypes.data) for a in arrays)

    def _plan(
        self, n_blocks: int, block_shape: tuple[int, int], keep: int, flags: int, *, stripped: bool
    ) -> tuple[int | None, ...]:
        """FFTW's plans on the arrays (see the class's ``plans``), None where
        FFTW could not plan; the caller holds the planner lock."""
        rows, cols = block_shape
        half = cols // 2 + 1
        real, spec, out, strip, strip_spec = self._addresses()
        shape = (ctypes.c_int * 2)(rows, cols)
        plans: tuple[int | None, ...] = (
            self._lib.fftwf_plan_many_dft_r2c(
                2, shape, n_blocks, real, None, 1, rows * cols, spec, None, 1, rows * half, flags,
            ),
            self._lib.fftwf_plan_guru_dft(
                1, _dims((rows, half, half)), 2,
                _dims((n_blocks, rows * half, rows * half), (half, 1, 1)),
                spec, spec, _BACKWARD, flags,
            ),
            self._lib.fftwf_plan_guru_dft_c2r(
                1, _dims((cols, 1, 1)), 2,
                _dims((n_blocks, rows * half, keep * cols), (keep, half, cols)),
                spec, out, flags,
            ),
        )  # fmt: skip
        if stripped:
            n_row = (ctypes.c_int * 1)(cols)
            plans += (
                self._lib.fftwf_plan_guru_dft(
                    1, _dims((rows, half, half)), 2,
                    _dims((n_blocks, rows * half, rows * half), (half, 1, 1)),
                    spec, spec, _FORWARD, flags,
                ),
                self._lib.fftwf_plan_many_dft_r2c(
                    1, n_row, STRIP_CHUNK, strip, None, 1, cols, strip_spec, None, 1, half, flags,
                ),
            )  # fmt: skip
        return plans

    def forward(self) -> None:
        """``spectrum = rfft2(real)`` over the last two axes (unnormalised)."""
        self._lib.fftwf_execute_dft_r2c(*self._forward_args)

    def inverse(self) -> None:
        """``out = irfft2(spectrum)[:, :out_rows] · rows · cols`` (unnormalised;
        destroys ``spectrum``)."""
        columns, rows = self._inverse_args
        self._lib.fftwf_execute_dft(*columns)
        self._lib.fftwf_execute_dft_c2r(*rows)

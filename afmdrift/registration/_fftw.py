"""FFTW plans and wisdom for the batched block transforms.

Plans are built once per block-stack shape by :class:`BatchedRealFFT` and kept
with their aligned input and output arrays. FFTW *wisdom* (the planner's
measurements) is loaded once per process from a file and written back after
new plans were made, so the second run of afmdrift plans in milliseconds.

The wisdom file is, in order of precedence, the ``fftw_wisdom`` setting of
:class:`~afmdrift.registration.RegistrationConfig`, the environment variable
``AFMDRIFT_FFTW_WISDOM``, or ``$XDG_CACHE_HOME/afmdrift/fftw-wisdom-<pyfftw
version>`` (``~/.cache`` when ``XDG_CACHE_HOME`` is unset). An empty string
disables wisdom. A missing, corrupt or unwritable file only logs a message.
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import pyfftw

__all__ = ["BatchedRealFFT", "default_wisdom_path", "resolve_wisdom_path"]

_log = logging.getLogger(__name__)

_MAGIC = b"afmdrift-fftw-wisdom 1\n"
_lock = threading.Lock()
_loaded: set[Path] = set()

Planner = Literal["estimate", "measure", "patient"]
_FLAGS: dict[str, str] = {
    "estimate": "FFTW_ESTIMATE",
    "measure": "FFTW_MEASURE",
    "patient": "FFTW_PATIENT",
}


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


class BatchedRealFFT:
    """Forward and inverse 2-D real FFTs over a stack of equal blocks.

    Parameters
    ----------
    n_blocks : int
        Batch size.
    block_shape : (int, int)
        ``(rows, cols)`` of each block.
    threads : int
        FFTW threads.
    planner : {"estimate", "measure", "patient"}
        FFTW planner effort.
    wisdom_path : Path or None
        Wisdom file to load before and update after planning.

    out_rows : int, optional
        Rows of the inverse transform's output that are needed, from the
        first (default: all). Fewer rows make :meth:`inverse` a pruned
        transform: the column transforms run over the whole spectrum, the
        row transforms only for the first ``out_rows`` rows (with half the
        rows, about 30 % less work than the full 2-D inverse).

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
    """

    def __init__(
        self,
        n_blocks: int,
        block_shape: tuple[int, int],
        *,
        threads: int = 1,
        planner: Planner = "measure",
        wisdom_path: Path | None = None,
        out_rows: int | None = None,
    ) -> None:
        rows, cols = block_shape
        spec_shape = (n_blocks, rows, cols // 2 + 1)
        self.real: npt.NDArray[np.float32] = pyfftw.empty_aligned(
            (n_blocks, rows, cols), dtype="float32"
        )
        self.spectrum: npt.NDArray[np.complex64] = pyfftw.empty_aligned(spec_shape, "complex64")
        pruned = out_rows is not None and out_rows < rows
        self.out: npt.NDArray[np.float32] = (
            pyfftw.empty_aligned((n_blocks, out_rows, cols), dtype="float32")
            if pruned
            else self.real
        )
        flags = (_FLAGS[planner], "FFTW_DESTROY_INPUT")
        with _lock:
            if wisdom_path is not None:
                _load_wisdom(wisdom_path)
            before = pyfftw.export_wisdom()
            self._forward = pyfftw.FFTW(
                self.real,
                self.spectrum,
                axes=(1, 2),
                direction="FFTW_FORWARD",
                flags=flags,
                threads=threads,
            )
            self._inverse: tuple[pyfftw.FFTW, ...]
            if pruned:
                self._inverse = (
                    pyfftw.FFTW(
                        self.spectrum,
                        self.spectrum,
                        axes=(1,),
                        direction="FFTW_BACKWARD",
                        flags=flags,
                        threads=threads,
                    ),
                    pyfftw.FFTW(
                        self.spectrum[:, :out_rows, :],
                        self.out,
                        axes=(2,),
                        direction="FFTW_BACKWARD",
                        flags=flags,
                        threads=threads,
                    ),
                )
            else:
                self._inverse = (
                    pyfftw.FFTW(
                        self.spectrum,
                        self.real,
                        axes=(1, 2),
                        direction="FFTW_BACKWARD",
                        flags=flags,
                        threads=threads,
                    ),
                )
            if wisdom_path is not None and pyfftw.export_wisdom() != before:
                _save_wisdom(wisdom_path)
        self.real.fill(0.0)
        self.out.fill(0.0)

    def forward(self) -> None:
        """``spectrum = rfft2(real)`` over the last two axes (unnormalised)."""
        self._forward.execute()

    def inverse(self) -> None:
        """``out = irfft2(spectrum)[:, :out_rows] · rows · cols`` (unnormalised;
        destroys ``spectrum``)."""
        for plan in self._inverse:
            plan.execute()

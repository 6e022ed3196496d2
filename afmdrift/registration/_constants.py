"""The constants of the compiled block kernels, in one record per frame
layout and configuration (:class:`KernelConstants`), made once by
:class:`~afmdrift.registration._engine.BlockEngine`.

Each kernel takes the part it needs (:class:`TransformConstants`,
:class:`SpectrumConstants`, :class:`PeakConstants`,
:class:`SubpixelConstants`); the compiled pass of a thread takes the whole
record. They are named tuples, which Numba compiles to plain structures:
reading a field costs nothing at run time.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.registration._blocks import BlockLayout, raised_cosine_axis
from afmdrift.registration._fftw import fftwf
from afmdrift.registration._subpixel import SUBPIXEL_CODES

__all__ = [
    "CANDIDATE_RATIO",
    "MAG_FLOOR",
    "NMS_RADIUS",
    "KernelConstants",
    "PeakConstants",
    "SpectrumConstants",
    "SubpixelConstants",
    "TransformConstants",
    "kernel_constants",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
IArr = npt.NDArray[np.intp]

#: Candidate peaks lower than this fraction of a block's highest peak are
#: not verified: at low SNR their MSE is as noisy as the right one's and would
#: only add wrong picks.
CANDIDATE_RATIO = 0.7
#: Half-size of the neighbourhood suppressed around each accepted peak (px).
NMS_RADIUS = 2
#: Absolute floor of the spectrum magnitude (its reciprocal, 1e30, is finite
#: in float32; any textured block's spectrum is many orders above it).
MAG_FLOOR = 1e-30


class TransformConstants(NamedTuple):
    """What the transforms need besides each thread's plans and arrays
    (:func:`afmdrift.registration._spectra.forward_strips`)."""

    #: The raised cosine's factors along the window's rows and columns, ``(Ey,)``
    #: and ``(Ex,)`` (the window is ``wy ⊗ wx``).
    wy: F32
    wx: F32
    #: Addresses of FFTW's r2c, c2c and c2r new-array execute functions
    #: (:class:`afmdrift.registration._fftw.Fftwf`), uint64.
    execute: npt.NDArray[np.uint64]


class SpectrumConstants(NamedTuple):
    """Mean removal, normalisation and the sub-pixel band
    (:func:`afmdrift.registration._spectra.normalise_reference`,
    :func:`~afmdrift.registration._spectra.normalise_cross`)."""

    #: The window's non-zero DFT terms: rows, columns ``(m,)`` and values
    #: ``(m, 2)`` as ``(re, im)``, float32; and the sum of the window
    #: (its zero-frequency term).
    w_rows: IArr
    w_cols: IArr
    w_vals: F32
    w_sum: float
    #: Magnitude floor ``max(eps_rel · max|S|, floor)`` per block.
    eps_rel: float
    floor: float
    #: The sub-pixel band: rows ``-ky..ky``, columns ``0..kx`` of the spectrum.
    ky: int
    kx: int
    #: Phase ramp ``exp(-2πi k·m)``, one block's spectrum shape, interleaved
    #: complex float32: every correlation comes out shifted by the search
    #: radius ``m``.
    ramp: F32


class PeakConstants(NamedTuple):
    """The peak search and its MSE check
    (:func:`afmdrift.registration._peaks.pick_peaks`)."""

    #: Most candidate peaks per block, the fraction of the block's highest
    #: peak a candidate needs, and the half-size of the suppressed squares (px).
    peaks: int
    ratio: float
    nms: int
    #: Offset ``(iy0, ix0)`` of the inner block in its window.
    inner: IArr
    #: The MSE lattice's rows and columns within the inner block.
    mse_rows: IArr
    mse_cols: IArr


class SubpixelConstants(NamedTuple):
    """The sub-pixel step (:mod:`afmdrift.registration._subpixel`)."""

    #: :data:`~afmdrift.registration._subpixel.SUBPIXEL_CODES` of ``config.subpixel``.
    method: int
    #: Frequencies of the band's rows (``-ky..ky``) and columns (``0..kx``),
    #: cycles/px.
    fy: F64
    fx: F64
    #: ``(my, mx)``: the shift the reference's phase ramp put into every
    #: correlation.
    shift: IArr
    #: Curvatures ``(κy, κx)`` of the window autocorrelation at zero shift.
    envelope: F64
    #: The inverse transform's scale: the correlation peak of identical
    #: blocks (the window's area, px²).
    scale: float


class KernelConstants(NamedTuple):
    """Every constant of the block kernels for one layout and configuration."""

    transform: TransformConstants
    spectrum: SpectrumConstants
    peaks: PeakConstants
    subpixel: SubpixelConstants


def kernel_constants(
    layout: BlockLayout, window: F32, config: RegistrationConfig
) -> KernelConstants:
    """The record for ``layout`` with the raised-cosine ``window`` (its
    ``layout.ext`` shape) and ``config``."""
    ey, ex = layout.ext
    by, bx = layout.block
    my, mx = layout.max_shift
    fftw = fftwf()
    transform = TransformConstants(
        wy=raised_cosine_axis(ey).astype(np.float32),
        wx=raised_cosine_axis(ex).astype(np.float32),
        execute=np.array([fftw.execute_r2c, fftw.execute_c2c, fftw.execute_c2r], dtype=np.uint64),
    )
    # Low-frequency band of the cross-power spectrum used by the "dft"
    # sub-pixel method (rfft layout: all ky in the band, kx >= 0).
    ky_max = max(1, int(config.subpixel_band * ey / 2))
    kx_max = max(1, int(config.subpixel_band * ex / 2))
    # The periodic raised cosine has a DFT with only a few non-zero terms;
    # removing the window-weighted block mean is a subtraction on them.
    wspec = np.fft.rfft2(window.astype(np.float64))
    nz = np.abs(wspec) > 1e-9 * abs(wspec[0, 0])
    w_rows, w_cols = (a.astype(np.intp) for a in np.nonzero(nz))
    # Phase ramp exp(-2πi k·m) folded into the reference spectra: every
    # correlation comes out shifted by the search radius m, so shifts
    # -m..m are rows and columns 0..2m of the (pruned) inverse FFT.
    ky_idx = np.arange(ey)[:, None]
    kx_idx = np.arange(ex // 2 + 1)[None, :]
    ramp = np.exp(-2j * np.pi * (ky_idx * my / ey + kx_idx * mx / ex))
    spectrum = SpectrumConstants(
        w_rows=w_rows,
        w_cols=w_cols,
        w_vals=np.column_stack([wspec[nz].real, wspec[nz].imag]).astype(np.float32),
        w_sum=float(wspec[0, 0].real),
        eps_rel=config.eps_rel,
        floor=MAG_FLOOR,
        ky=ky_max,
        kx=kx_max,
        ramp=ramp.astype(np.complex64).view(np.float32),
    )
    stride = config.mse_stride_px
    peaks = PeakConstants(
        peaks=config.peaks,
        ratio=CANDIDATE_RATIO,
        nms=NMS_RADIUS,
        inner=np.array([(ey - by) // 2, (ex - bx) // 2], dtype=np.intp),
        mse_rows=np.arange(0, by, stride, dtype=np.intp),
        mse_cols=np.arange(0, bx, stride, dtype=np.intp),
    )
    # Curvature κ of the window autocorrelation A(s) = Σ w(x) w(x+s) / Σ w²
    # near s = 0 (per axis): the correlation of windowed blocks is about
    # A(p)·C(p - d), so its maximum is pulled towards p = 0 unless A is
    # divided out.
    wy = window.sum(axis=1).astype(np.float64)
    wx = window.sum(axis=0).astype(np.float64)
    subpixel = SubpixelConstants(
        method=SUBPIXEL_CODES[config.subpixel],
        fy=np.arange(-ky_max, ky_max + 1) / ey,
        fx=np.arange(0, kx_max + 1) / ex,
        shift=np.array([my, mx], dtype=np.intp),
        envelope=np.array(
            [
                np.sum(np.diff(wy) ** 2) / np.sum(wy**2),
                np.sum(np.diff(wx) ** 2) / np.sum(wx**2),
            ]
        ),
        scale=float(ey * ex),
    )
    return KernelConstants(transform=transform, spectrum=spectrum, peaks=peaks, subpixel=subpixel)

"""Synthetic AFM height textures and exact sub-pixel shifts.

Every texture here is *periodic* and (nearly) band-limited, so that a Fourier
phase ramp shifts it exactly by any sub-pixel amount. To imitate a real AFM,
where drift moves content in at one edge and out at the other, generate a
texture larger than the frame and cut frames out of shifted copies with
:func:`shifted_crop`; nothing wraps around inside the frame as long as the
shift stays within the margin.

Conventions follow :mod:`afmdrift.registration`: images are ``[row, col]``,
x runs along columns and y along rows, and a shift ``(dx_px, dy_px)`` moves a
feature at ``u`` to ``u + d``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "DISTORTIONS",
    "Particles",
    "TextureShifter",
    "add_line_offsets",
    "add_noise",
    "add_plane",
    "band_limit",
    "distorted_crop",
    "distortion_field",
    "fourier_shift",
    "lattice_texture",
    "particle_texture",
    "rough_texture",
    "shifted_crop",
    "terrace_texture",
]

FloatArray = npt.NDArray[np.float64]

#: Factor from full width at half maximum to Gaussian standard deviation.
_FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def _check_shape(shape: tuple[int, int]) -> tuple[int, int]:
    rows, cols = (int(shape[0]), int(shape[1]))
    if rows < 2 or cols < 2:
        raise ValueError(f"shape must be at least (2, 2), got {shape!r}")
    return rows, cols


def band_limit(image: npt.ArrayLike) -> FloatArray:
    """Remove the Nyquist row and column of a periodic image.

    Those are the only components whose sub-pixel shift is ambiguous for a
    real image, so afterwards :func:`fourier_shift` is exact. Every texture
    of this module is returned band-limited this way.
    """
    img = np.asarray(image, dtype=np.float64)
    rows, cols = img.shape
    spec = np.fft.rfft2(img)
    if rows % 2 == 0:
        spec[rows // 2, :] = 0.0
    if cols % 2 == 0:
        spec[:, cols // 2] = 0.0
    out: FloatArray = np.fft.irfft2(spec, s=(rows, cols))
    return out


def fourier_shift(image: npt.ArrayLike, *, dx_px: float, dy_px: float) -> FloatArray:
    """Shift a periodic image by a sub-pixel amount with a Fourier phase ramp.

    A feature at ``(x, y)`` moves to ``(x + dx_px, y + dy_px)``, wrapping
    around the edges. The shift is exact for band-limited periodic images
    (all textures of this module). The Nyquist row/column, whose phase is
    ambiguous for a real signal, is kept real (its shifted value is the
    real part).

    Parameters
    ----------
    image : array_like, shape (rows, cols)
        Real image.
    dx_px, dy_px : float
        Shift along x (columns) and y (rows) in pixels.

    Returns
    -------
    ndarray, shape (rows, cols), float64
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    rows, cols = img.shape
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.rfftfreq(cols)[None, :]
    ramp = np.exp(-2j * np.pi * (kx * dx_px + ky * dy_px))
    return np.fft.irfft2(np.fft.rfft2(img) * ramp, s=(rows, cols))


class TextureShifter:
    """Cut frames out of exactly shifted copies of one large periodic texture.

    The texture's spectrum is computed once, so each frame costs a single
    inverse FFT; :func:`shifted_crop` is the one-off form.

    Parameters
    ----------
    texture : array_like, shape (rows, cols)
        Periodic, band-limited texture (any texture of this module).
    """

    def __init__(self, texture: npt.ArrayLike) -> None:
        tex = np.asarray(texture, dtype=np.float64)
        if tex.ndim != 2:
            raise ValueError(f"texture must be 2-D, got shape {tex.shape}")
        self.shape: tuple[int, int] = (int(tex.shape[0]), int(tex.shape[1]))
        self._spec = np.fft.rfft2(tex)
        self._ky = np.fft.fftfreq(self.shape[0])[:, None]
        self._kx = np.fft.rfftfreq(self.shape[1])[None, :]

    def crop(
        self,
        shape: tuple[int, int],
        *,
        dx_px: float = 0.0,
        dy_px: float = 0.0,
        origin_px: tuple[int, int] | None = None,
    ) -> FloatArray:
        """The frame ``shape`` at ``origin_px`` (``(col, row)`` of its top-left
        corner; default: centred) of the texture shifted by ``(dx_px, dy_px)``.

        Raises
        ------
        ValueError
            If the window does not fit, or the shift is larger than the margin
            between window and texture edge (wrapped content would enter).
        """
        rows, cols = _check_shape(shape)
        t_rows, t_cols = self.shape
        if origin_px is None:
            origin_px = ((t_cols - cols) // 2, (t_rows - rows) // 2)
        x0, y0 = int(origin_px[0]), int(origin_px[1])
        if x0 < 0 or y0 < 0 or x0 + cols > t_cols or y0 + rows > t_rows:
            raise ValueError(
                f"frame {shape} at origin {origin_px} does not fit in texture {self.shape}"
            )
        margin_x = min(x0, t_cols - cols - x0)
        margin_y = min(y0, t_rows - rows - y0)
        if abs(dx_px) > margin_x or abs(dy_px) > margin_y:
            raise ValueError(
                f"shift ({dx_px}, {dy_px}) px exceeds the texture margin "
                f"({margin_x}, {margin_y}) px"
            )
        ramp = np.exp(-2j * np.pi * (self._kx * dx_px + self._ky * dy_px))
        shifted = np.fft.irfft2(self._spec * ramp, s=self.shape)
        out: FloatArray = shifted[y0 : y0 + rows, x0 : x0 + cols].copy()
        return out


def shifted_crop(
    texture: npt.ArrayLike,
    *,
    shape: tuple[int, int],
    dx_px: float = 0.0,
    dy_px: float = 0.0,
    origin_px: tuple[int, int] | None = None,
) -> FloatArray:
    """Cut a frame out of a shifted copy of a larger periodic texture.

    The frame is the window ``shape`` at ``origin_px`` (``(col, row)`` of its
    top-left corner; default: centred) of ``fourier_shift(texture, dx_px,
    dy_px)``. Content therefore enters and leaves at the frame edges as with
    a real drifting scan. See :class:`TextureShifter` for many frames.

    Raises
    ------
    ValueError
        If the window does not fit, or the shift is larger than the margin
        between window and texture edge (wrapped content would enter).
    """
    return TextureShifter(texture).crop(shape, dx_px=dx_px, dy_px=dy_px, origin_px=origin_px)


#: Distortions :func:`distorted_crop` makes (a non-rigid frame).
DISTORTIONS = ("bow_x", "bow_y", "rotation", "creep")


def distortion_field(
    shape: tuple[int, int], kind: str, amplitude_px: float
) -> tuple[FloatArray, FloatArray]:
    """Displacement ``(Dx, Dy)`` (px, per pixel of a frame ``shape``) of a
    non-rigid scan, zero-mean over the frame, ``amplitude_px`` its range
    (peak to peak) across the frame:

    - ``bow_x``: fast-axis nonlinearity (the scanner's x position bows with
      x: features on both sides lie farther out), ``Dx = A (u² − 1/3)``;
    - ``bow_y``: bowed scan lines (each line's y position bows with x),
      ``Dy = A (u² − 1/3)``;
    - ``rotation``: a small rotation about the centre, ``A`` across the
      frame's width;
    - ``creep``: logarithmic creep along the slow axis after a move,
      ``Dy = A (ln(1 + 8 v) / ln 9 − mean)``, which the trend over the rows
      follows (the control of a distortion sweep);

    with ``u = (x − cx) / (cols / 2)`` and ``v = y / rows``."""
    rows, cols = _check_shape(shape)
    y, x = np.mgrid[:rows, :cols].astype(np.float64)
    u = (x - (cols - 1) / 2) / (cols / 2)
    zero = np.zeros((rows, cols))
    if kind == "bow_x":
        return amplitude_px * (u * u - float(np.mean(u * u))), zero
    if kind == "bow_y":
        return zero, amplitude_px * (u * u - float(np.mean(u * u)))
    if kind == "rotation":
        theta = amplitude_px / cols
        return -theta * (y - (rows - 1) / 2), theta * (x - (cols - 1) / 2)
    if kind == "creep":
        c = np.log1p(8.0 * y / rows) / math.log(9.0)
        return zero, amplitude_px * (c - float(c.mean()))
    raise ValueError(f"unknown distortion {kind!r}; expected one of {DISTORTIONS}")


def distorted_crop(
    texture: npt.ArrayLike,
    shape: tuple[int, int],
    *,
    dx_px: float = 0.0,
    dy_px: float = 0.0,
    kind: str = "bow_x",
    amplitude_px: float = 0.0,
) -> FloatArray:
    """The centred frame ``shape`` of a periodic ``texture`` moved by ``(dx_px,
    dy_px)`` and distorted by :func:`distortion_field` (a feature at ``u`` in
    the undistorted, unmoved frame appears at ``u + d + D``): the drift of the
    frame, taken over its area, is ``d`` exactly (``D`` is zero-mean). Sampled
    by a cubic spline of the (band-limited) texture; cut the reference with
    ``amplitude_px = 0`` so both frames are sampled alike."""
    from scipy.ndimage import map_coordinates

    tex = np.asarray(texture, dtype=np.float64)
    rows, cols = _check_shape(shape)
    t_rows, t_cols = tex.shape
    x0, y0 = (t_cols - cols) // 2, (t_rows - rows) // 2
    ddx, ddy = distortion_field((rows, cols), kind, amplitude_px)
    y, x = np.mgrid[:rows, :cols].astype(np.float64)
    # the content at frame pixel p came from p - d - D(p) (to first order in D)
    coords = np.array([y0 + y - dy_px - ddy, x0 + x - dx_px - ddx])
    out: FloatArray = map_coordinates(tex, coords, order=3, mode="grid-wrap")
    return out


@dataclass(frozen=True)
class Particles:
    """Round particles (gold-colloid-like) on a flat substrate.

    Each particle is a Gaussian bump, a fair model of a ~30 nm sphere imaged
    by a tip of similar radius. Rendering is periodic over the canvas.

    Attributes
    ----------
    x_px, y_px : ndarray, shape (n,)
        Centres in pixels (x along columns).
    height_nm : ndarray, shape (n,)
        Peak heights.
    fwhm_px : float
        Full width at half maximum of every bump, in pixels.
    """

    x_px: FloatArray
    y_px: FloatArray
    height_nm: FloatArray
    fwhm_px: float

    @classmethod
    def random(
        cls,
        shape: tuple[int, int],
        *,
        pixel_size_nm: float,
        rng: np.random.Generator,
        density_per_um2: float = 150.0,
        diameter_nm: float = 30.0,
    ) -> Particles:
        """Uniformly scattered particles, heights ``diameter_nm`` ± 10 %."""
        rows, cols = _check_shape(shape)
        area_um2 = rows * cols * (pixel_size_nm * 1e-3) ** 2
        n = max(1, int(rng.poisson(density_per_um2 * area_um2)))
        return cls(
            x_px=rng.uniform(0, cols, n),
            y_px=rng.uniform(0, rows, n),
            height_nm=diameter_nm * rng.normal(1.0, 0.1, n),
            fwhm_px=diameter_nm / pixel_size_nm,
        )

    def render(self, shape: tuple[int, int]) -> FloatArray:
        """Periodic height image, shape ``shape``, in nm."""
        rows, cols = _check_shape(shape)
        sigma = self.fwhm_px * _FWHM_TO_SIGMA
        half = int(np.ceil(5.0 * sigma))
        out = np.zeros((rows, cols))
        offs = np.arange(-half, half + 1)
        for x, y, h in zip(self.x_px, self.y_px, self.height_nm, strict=True):
            ix, iy = int(np.floor(x)), int(np.floor(y))
            gx = np.exp(-0.5 * ((ix + offs - x) / sigma) ** 2)
            gy = np.exp(-0.5 * ((iy + offs - y) / sigma) ** 2)
            out[np.ix_((iy + offs) % rows, (ix + offs) % cols)] += h * np.outer(gy, gx)
        return out


def rough_texture(
    shape: tuple[int, int],
    *,
    pixel_size_nm: float,
    rng: np.random.Generator,
    rms_nm: float = 1.0,
    correlation_length_nm: float = 20.0,
) -> FloatArray:
    """Periodic Gaussian random rough surface with a Gaussian autocorrelation.

    White noise filtered in Fourier space by ``exp(-(π k ℓ)²/... )``; the
    result is scaled to ``rms_nm``. Band-limited when ``ℓ`` spans a few pixels.
    """
    rows, cols = _check_shape(shape)
    ell_px = correlation_length_nm / pixel_size_nm
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.rfftfreq(cols)[None, :]
    # Gaussian autocorrelation exp(-r²/ℓ²) has power spectrum ∝ exp(-(π ℓ k)²).
    filt = np.exp(-0.5 * (np.pi * ell_px) ** 2 * (kx**2 + ky**2))
    spec = np.fft.rfft2(rng.standard_normal((rows, cols))) * filt
    h = band_limit(np.fft.irfft2(spec, s=(rows, cols)))
    h -= h.mean()
    h *= rms_nm / h.std()
    return h


def terrace_texture(
    shape: tuple[int, int],
    *,
    pixel_size_nm: float,
    rng: np.random.Generator,
    step_height_nm: float = 0.335,
    terrace_width_nm: float = 80.0,
    step_width_px: float = 1.5,
    roughness_nm: float = 0.02,
) -> FloatArray:
    """Graphite-like terraces: flat levels separated by monatomic steps.

    The level map is a smooth periodic random field quantised into steps of
    ``step_height_nm`` (0.335 nm: one graphene layer); each step is smoothed
    over about ``step_width_px`` so the texture stays band-limited enough for
    exact Fourier shifts. A faint roughness keeps terraces from being
    perfectly flat.
    """
    terrace_px = terrace_width_nm / pixel_size_nm
    field = rough_texture(
        shape,
        pixel_size_nm=pixel_size_nm,
        rng=rng,
        rms_nm=1.0,
        correlation_length_nm=terrace_width_nm,
    )
    # Scale the field so that it rises by one level per terrace width.
    mean_slope = float(np.mean(np.hypot(*np.gradient(field))))
    levels = field / (mean_slope * terrace_px)
    # Soft staircase: floor() with each unit step replaced by a tanh ramp
    # about step_width_px wide (in level units: step_width_px / terrace_px).
    half_width = 0.5 * step_width_px / terrace_px
    frac = levels - np.floor(levels)
    stairs = np.floor(levels) + 0.5 * (1.0 + np.tanh((frac - 0.5) / half_width))
    h = step_height_nm * stairs
    h += rough_texture(
        shape,
        pixel_size_nm=pixel_size_nm,
        rng=rng,
        rms_nm=roughness_nm,
        correlation_length_nm=3.0 * pixel_size_nm,
    )
    h = band_limit(h)
    h -= h.mean()
    return h


def particle_texture(
    shape: tuple[int, int],
    *,
    pixel_size_nm: float,
    rng: np.random.Generator,
    density_per_um2: float = 150.0,
    diameter_nm: float = 30.0,
    substrate_rms_nm: float = 0.2,
) -> FloatArray:
    """Gold-particle-like bumps scattered on a slightly rough flat substrate."""
    parts = Particles.random(
        shape,
        pixel_size_nm=pixel_size_nm,
        rng=rng,
        density_per_um2=density_per_um2,
        diameter_nm=diameter_nm,
    )
    substrate = rough_texture(
        shape,
        pixel_size_nm=pixel_size_nm,
        rng=rng,
        rms_nm=substrate_rms_nm,
        correlation_length_nm=2.0 * pixel_size_nm,
    )
    return band_limit(parts.render(shape)) + substrate


def lattice_texture(
    shape: tuple[int, int],
    *,
    rng: np.random.Generator,
    period_px: float = 10.3,
    angle_deg: float = 11.0,
    dot_fwhm_px: float = 3.5,
    height_nm: float = 1.0,
    vacancy_fraction: float = 0.0,
    jitter_px: float = 0.0,
) -> FloatArray:
    """A periodic sample: an oblique lattice of round dots (a crystal surface,
    a grating of posts), periodic over the canvas so that every shift of it is
    exact.

    The lattice is given by two reciprocal vectors of length ``1/period_px``
    (cycles per px), the first at ``angle_deg`` from the y axis and the second
    65° from it (an oblique lattice, like the real NanoScope frame's with its
    period of about 10 px along one axis), each rounded to whole cycles over
    the canvas so that the lattice tiles it. A dot of ``height_nm`` sits at
    every lattice point; ``vacancy_fraction`` of them are missing and every
    dot is displaced by Gaussian ``jitter_px`` (defects, which let the
    content tell lattice translations apart; a perfect lattice has none, and
    its translations cannot be told apart by any method).
    """
    rows, cols = _check_shape(shape)
    if not period_px >= 2:
        raise ValueError(f"period_px must be at least 2, got {period_px}")
    if not 0 <= vacancy_fraction < 1:
        raise ValueError(f"vacancy_fraction must be in [0, 1), got {vacancy_fraction}")
    # integer cycles over the canvas (kx · cols, ky · rows) of each reciprocal vector
    cycles = []
    for deg in (angle_deg, angle_deg + 65.0):
        t = np.deg2rad(deg)
        cycles.append((round(np.sin(t) * cols / period_px), round(-np.cos(t) * rows / period_px)))
    recip = np.array([[m / cols, n / rows] for m, n in cycles])  # rows: G1, G2 (x, y)
    det = round(cycles[0][0] * cycles[1][1] - cycles[0][1] * cycles[1][0])
    if det == 0:
        raise ValueError(f"period_px {period_px} and angle {angle_deg} give no 2-D lattice")
    basis = np.linalg.inv(recip)  # columns: the lattice vectors a1, a2 (x, y)
    # The canvas holds |det| lattice points; walk integer combinations until
    # every one (modulo the canvas) is found.
    reach = abs(det) + 1
    i, j = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1))
    pts = basis @ np.vstack([i.ravel(), j.ravel()])
    xy = np.round(np.column_stack([pts[0], pts[1]]), 6) % (cols, rows)
    xy = np.unique(np.round(xy, 6) % (cols, rows), axis=0)
    keep = rng.random(len(xy)) >= vacancy_fraction
    xy = xy[keep] + rng.normal(0.0, jitter_px, (int(keep.sum()), 2)) * (jitter_px > 0)
    dots = Particles(
        x_px=xy[:, 0] % cols,
        y_px=xy[:, 1] % rows,
        height_nm=np.full(len(xy), height_nm),
        fwhm_px=dot_fwhm_px,
    )
    h = band_limit(dots.render((rows, cols)))
    h -= h.mean()
    return h


def add_noise(image: npt.ArrayLike, *, snr: float, rng: np.random.Generator) -> FloatArray:
    """Add white Gaussian height noise at a signal-to-noise ratio.

    SNR is defined on heights: ``std(image) / std(noise)``.
    """
    img = np.asarray(image, dtype=np.float64)
    if not snr > 0:
        raise ValueError(f"snr must be > 0, got {snr}")
    return img + rng.normal(0.0, float(img.std()) / snr, img.shape)


def add_plane(
    image: npt.ArrayLike, *, offset_nm: float = 0.0, slope_x: float = 0.0, slope_y: float = 0.0
) -> FloatArray:
    """Add a z offset and a tilt plane ``offset + slope_x·x + slope_y·y`` (nm per px)."""
    img = np.asarray(image, dtype=np.float64)
    rows, cols = img.shape
    y, x = np.mgrid[0:rows, 0:cols]
    out: FloatArray = img + offset_nm + slope_x * x + slope_y * y
    return out


def add_line_offsets(
    image: npt.ArrayLike, *, rms_nm: float, rng: np.random.Generator
) -> FloatArray:
    """Add an independent random height offset to every scan line (row)."""
    img = np.asarray(image, dtype=np.float64)
    return img + rng.normal(0.0, rms_nm, (img.shape[0], 1))

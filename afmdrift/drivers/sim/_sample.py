"""Sample surfaces for the simulated AFM: gold particles on mica, graphite terraces,
or any height image as a texture.

A sample is a periodic height map (larger than the scan area, so drift moves
content in and out of view) plus a layer of particles that the tip can push.
Heights are read at arbitrary positions by cubic B-spline interpolation of the
map (coefficients computed once, periodic boundary), which is accurate to far
below 0.05 px for the band-limited surfaces built here: every sharp feature is
smoothed by at least ``edge_sigma_px`` map pixels, as the tip apex does on a real
instrument.

Particles are drawn as Gaussians of height ``d`` (the particle diameter) and
standard deviation ``σ = √(R_p R_t)``: a sphere of radius ``R_p`` imaged by a
tip of apex radius ``R_t`` appears with a base width ``4 √(R_p R_t)`` (the
standard sphere–sphere tip-convolution geometry; Villarrubia, J. Res. NIST 102,
425 (1997)), and the Gaussian's ±2σ span matches it.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from afmdrift.drivers.sim._scenario import SampleConfig
from afmdrift.errors import ConfigError
from afmdrift.io import load_image

__all__ = ["Sample", "gaussian_field", "periodic_component"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


def gaussian_field(shape: tuple[int, int], corr_px: float, rng: np.random.Generator) -> FloatArray:
    """Periodic Gaussian random field with unit std and Gaussian correlation.

    Parameters
    ----------
    shape : (rows, cols)
    corr_px : float
        Correlation length (std of the Gaussian smoothing kernel) in pixels.
    rng : numpy Generator
    """
    noise = rng.standard_normal(shape)
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.rfftfreq(shape[1])[None, :]
    kernel = np.exp(-2.0 * (np.pi * corr_px) ** 2 * (kx * kx + ky * ky))
    field = np.fft.irfft2(np.fft.rfft2(noise) * kernel, s=shape)
    std = float(field.std())
    out: FloatArray = (field - field.mean()) / (std if std > 0 else 1.0)
    return out


def _smooth_periodic(a: FloatArray, sigma_px: float) -> FloatArray:
    ky = np.fft.fftfreq(a.shape[0])[:, None]
    kx = np.fft.rfftfreq(a.shape[1])[None, :]
    kernel = np.exp(-2.0 * (np.pi * sigma_px) ** 2 * (kx * kx + ky * ky))
    out: FloatArray = np.fft.irfft2(np.fft.rfft2(a) * kernel, s=a.shape)
    return out


def periodic_component(image: npt.ArrayLike) -> FloatArray:
    """Periodic part of an image (periodic-plus-smooth decomposition).

    Removes the smooth component that carries the jumps across opposite
    borders, so the image tiles the plane without seams. Method: L. Moisan,
    "Periodic plus smooth image decomposition", J. Math. Imaging Vis. 39,
    161–179 (2011).

    Parameters
    ----------
    image : array_like, shape (rows, cols)
    """
    u = np.asarray(image, dtype=np.float64)
    rows, cols = u.shape
    v = np.zeros_like(u)
    v[0, :] += u[-1, :] - u[0, :]
    v[-1, :] += u[0, :] - u[-1, :]
    v[:, 0] += u[:, -1] - u[:, 0]
    v[:, -1] += u[:, 0] - u[:, -1]
    q = np.arange(rows)[:, None]
    r = np.arange(cols)[None, :]
    denom = 2.0 * np.cos(2.0 * np.pi * q / rows) + 2.0 * np.cos(2.0 * np.pi * r / cols) - 4.0
    denom[0, 0] = 1.0
    s_hat = np.fft.fft2(v) / denom
    s_hat[0, 0] = 0.0
    smooth = np.real(np.fft.ifft2(s_hat))
    out: FloatArray = u - smooth
    return out


class Sample:
    """A periodic sample surface with pushable particles.

    Parameters
    ----------
    base_nm : ndarray, shape (rows, cols)
        Periodic substrate heights in nm on a grid of spacing ``grid_nm``.
    grid_nm : (float, float)
        Map spacing along x (columns) and y (rows), nm.
    particles : ndarray, shape (n, 3)
        Particle centres ``x_nm, y_nm`` (sample coordinates) and diameters ``d_nm``.
    tip_radius_nm : float
        Tip apex radius, sets the particles' apparent width.
    min_sigma_px : float
        Smallest Gaussian width of a particle, in map pixels (keeps the map
        band-limited).
    """

    def __init__(
        self,
        base_nm: npt.ArrayLike,
        *,
        grid_nm: tuple[float, float],
        particles: npt.ArrayLike | None = None,
        tip_radius_nm: float = 10.0,
        min_sigma_px: float = 1.0,
    ) -> None:
        self.base_nm = np.asarray(base_nm, dtype=np.float64)
        if self.base_nm.ndim != 2:
            raise ValueError(f"base_nm must be 2-D, got shape {self.base_nm.shape}")
        self.grid_nm = (float(grid_nm[0]), float(grid_nm[1]))
        self.tip_radius_nm = float(tip_radius_nm)
        self.min_sigma_px = float(min_sigma_px)
        p = np.zeros((0, 3)) if particles is None else np.asarray(particles, dtype=np.float64)
        self.particles = p.reshape(-1, 3).copy()
        rows, cols = self.base_nm.shape
        self.extent_nm = (cols * self.grid_nm[0], rows * self.grid_nm[1])
        self.particles[:, 0] %= self.extent_nm[0]
        self.particles[:, 1] %= self.extent_nm[1]
        self._layer = np.zeros_like(self.base_nm)
        for k in range(len(self.particles)):
            self._stamp(k, +1.0)
        self._coeffs = self._filter()

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_config(cls, cfg: SampleConfig, *, seed: int) -> Sample:
        """Build the sample a scenario describes (deterministic for ``seed``)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5A3F]))
        if cfg.kind == "texture":
            return cls._from_texture(cfg)
        n = cfg.map_px
        shape = (n, n)
        g = cfg.grid_nm
        area_um2 = (n * g) ** 2 * 1e-6
        base = np.zeros(shape)
        if cfg.roughness_nm > 0:
            base += cfg.roughness_nm * gaussian_field(shape, cfg.roughness_corr_nm / g, rng)
        if cfg.kind == "gold_on_mica":
            p = cfg.gold
            count = int(rng.poisson(p.density_per_um2 * area_um2))
            diam = np.maximum(
                rng.normal(p.particle_diameter_nm, p.diameter_sigma_nm, count),
                0.2 * p.particle_diameter_nm,
            )
        else:
            gp = cfg.graphite
            angle = (
                float(rng.uniform(0.0, 180.0))
                if gp.step_direction_deg is None
                else gp.step_direction_deg
            )
            base += _terraces(
                shape,
                gp.terrace_width_nm / g,
                gp.step_height_nm,
                rng,
                direction_deg=angle,
                meander=gp.meander,
            )
            base = _smooth_periodic(base, cfg.edge_sigma_px)
            count = int(rng.poisson(gp.debris_density_per_um2 * area_um2))
            diam = np.abs(rng.normal(gp.debris_diameter_nm, 0.3 * gp.debris_diameter_nm, count))
            diam = np.maximum(diam, 0.2 * gp.debris_diameter_nm)
        xy = rng.uniform(0.0, n * g, (count, 2))
        particles = np.column_stack([xy, diam])
        return cls(
            base,
            grid_nm=(g, g),
            particles=particles,
            tip_radius_nm=cfg.tip_radius_nm,
            min_sigma_px=cfg.edge_sigma_px,
        )

    @classmethod
    def from_image(
        cls,
        heights_nm: npt.ArrayLike,
        *,
        pixel_size_nm: tuple[float, float],
        tip_radius_nm: float = 10.0,
        edge_sigma_px: float = 1.0,
    ) -> Sample:
        """A sample whose surface is a height image (e.g. a real AFM image).

        The image is made periodic (:func:`periodic_component`), its mean removed,
        and smoothed by ``edge_sigma_px − 0.5`` px if that is positive.

        Parameters
        ----------
        heights_nm : array_like, shape (rows, cols)
            Finite heights in nm, at least 16×16 px.
        pixel_size_nm : (float, float)
            Pixel size of the image along x and y, nm.

        Raises
        ------
        ValueError
            The image is not a finite 2-D array of at least 16×16 px, or a pixel
            size is not positive.
        """
        heights = np.asarray(heights_nm, dtype=np.float64)
        if heights.ndim != 2 or min(heights.shape) < 16 or not np.all(np.isfinite(heights)):
            raise ValueError(
                f"need a finite 2-D height image of at least 16x16 px, got shape {heights.shape}"
            )
        if not all(math.isfinite(v) and v > 0 for v in pixel_size_nm):
            raise ValueError(f"pixel_size_nm must be positive, got {pixel_size_nm}")
        base = periodic_component(heights - heights.mean())
        if edge_sigma_px > 0.5:
            base = _smooth_periodic(base, edge_sigma_px - 0.5)
        return cls(
            base,
            grid_nm=(float(pixel_size_nm[0]), float(pixel_size_nm[1])),
            tip_radius_nm=tip_radius_nm,
            min_sigma_px=edge_sigma_px,
        )

    @classmethod
    def _from_texture(cls, cfg: SampleConfig) -> Sample:
        assert cfg.texture is not None
        path = Path(cfg.texture.path)
        where = f"sample.texture.path = {str(path)!r}"
        pixel_nm: tuple[float, float] | None = cfg.texture.pixel_size_nm
        if path.suffix.lower() == ".npy":
            try:
                heights = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as err:
                raise ConfigError(f"{where}: cannot read: {err}") from None
        else:
            heights, file_pixel_nm = _load_with_afmdrift_io(path)
            pixel_nm = pixel_nm or file_pixel_nm
        try:
            return cls.from_image(
                heights,
                pixel_size_nm=pixel_nm or (cfg.grid_nm, cfg.grid_nm),
                tip_radius_nm=cfg.tip_radius_nm,
                edge_sigma_px=cfg.edge_sigma_px,
            )
        except ValueError as err:
            raise ConfigError(f"{where}: {err}") from None

    # ------------------------------------------------------------------ particles

    def particle_sigma_px(self, diameter_nm: float) -> tuple[float, float]:
        """Gaussian std (x, y) of a particle's footprint in map pixels: √(R_p R_t), at least
        ``min_sigma_px``."""
        sigma_nm = math.sqrt(0.5 * diameter_nm * self.tip_radius_nm)
        return (
            max(sigma_nm / self.grid_nm[0], self.min_sigma_px),
            max(sigma_nm / self.grid_nm[1], self.min_sigma_px),
        )

    def _stamp(self, k: int, sign: float) -> None:
        """Add (sign=+1) or remove (-1) particle k's footprint in the particle layer."""
        x_nm, y_nm, d_nm = self.particles[k]
        sx, sy = self.particle_sigma_px(float(d_nm))
        cx, cy = x_nm / self.grid_nm[0], y_nm / self.grid_nm[1]
        hx, hy = math.ceil(5 * sx), math.ceil(5 * sy)
        ix = np.arange(math.floor(cx) - hx, math.floor(cx) + hx + 2)
        iy = np.arange(math.floor(cy) - hy, math.floor(cy) + hy + 2)
        gx = np.exp(-0.5 * ((ix - cx) / sx) ** 2)
        gy = np.exp(-0.5 * ((iy - cy) / sy) ** 2)
        rows, cols = self._layer.shape
        self._layer[np.ix_(iy % rows, ix % cols)] += sign * d_nm * np.outer(gy, gx)

    def _filter(self) -> FloatArray:
        coeffs: FloatArray = ndimage.spline_filter(
            self.base_nm + self._layer, order=3, mode="grid-wrap", output=np.float64
        )
        return coeffs

    def set_tip_radius(self, tip_radius_nm: float) -> None:
        """Change the tip apex radius (re-renders the particles' apparent widths)."""
        self.tip_radius_nm = float(tip_radius_nm)
        self._layer[...] = 0.0
        for k in range(len(self.particles)):
            self._stamp(k, +1.0)
        self._coeffs = self._filter()

    def _minimal_image(self, d: FloatArray) -> FloatArray:
        ext = np.asarray(self.extent_nm)
        out: FloatArray = (d + 0.5 * ext) % ext - 0.5 * ext
        return out

    def nearest_particle(self, x_nm: float, y_nm: float) -> tuple[int, float]:
        """Index of the particle nearest to a sample position, and its distance (nm)."""
        if len(self.particles) == 0:
            return -1, math.inf
        d = self._minimal_image(self.particles[:, :2] - np.array([x_nm, y_nm]))
        dist = np.hypot(d[:, 0], d[:, 1])
        k = int(np.argmin(dist))
        return k, float(dist[k])

    def particle_offset(self, k: int, x_nm: float, y_nm: float) -> tuple[float, float]:
        """Vector from a sample position to particle ``k`` (minimal periodic image), nm."""
        d = self._minimal_image(self.particles[k, :2] - np.array([x_nm, y_nm]))
        return float(d[0]), float(d[1])

    def push(self, x0_nm: float, y0_nm: float, x1_nm: float, y1_nm: float) -> list[int]:
        """Sweep the tip from (x0, y0) to (x1, y1) in sample coordinates.

        A particle whose centre lies within the contact distance ``R_p + R_t`` of
        the path (and ahead of the start) is carried along the path until its
        projection on the path reaches the end point; its lateral offset is kept.
        Returns the indices of the moved particles.
        """
        a = np.array([x0_nm, y0_nm])
        path = np.array([x1_nm - x0_nm, y1_nm - y0_nm])
        length = float(np.hypot(*path))
        if length == 0.0 or len(self.particles) == 0:
            return []
        u = path / length
        rel = self._minimal_image(self.particles[:, :2] - a)
        along = rel @ u
        across = rel[:, 0] * u[1] - rel[:, 1] * u[0]
        contact = 0.5 * self.particles[:, 2] + self.tip_radius_nm
        hit = (np.abs(across) < contact) & (along > -contact) & (along < length)
        moved = [int(k) for k in np.nonzero(hit)[0]]
        for k in moved:
            self._stamp(k, -1.0)
            self.particles[k, :2] += (length - along[k]) * u
            self.particles[k, 0] %= self.extent_nm[0]
            self.particles[k, 1] %= self.extent_nm[1]
            self._stamp(k, +1.0)
        if moved:
            self._coeffs = self._filter()
        return moved

    # ------------------------------------------------------------------ sampling

    def heights_at(self, x_nm: npt.ArrayLike, y_nm: npt.ArrayLike) -> FloatArray:
        """Surface height (nm) at sample positions, by periodic cubic B-spline interpolation.

        ``x_nm`` and ``y_nm`` broadcast together; the result has their shape.
        """
        x, y = np.broadcast_arrays(np.asarray(x_nm, np.float64), np.asarray(y_nm, np.float64))
        coords = np.stack([y / self.grid_nm[1], x / self.grid_nm[0]])
        out: FloatArray = ndimage.map_coordinates(
            self._coeffs, coords, order=3, mode="grid-wrap", prefilter=False, output=np.float64
        )
        return out


def _terraces(
    shape: tuple[int, int],
    width_px: float,
    step_nm: float,
    rng: np.random.Generator,
    *,
    direction_deg: float,
    meander: float,
) -> FloatArray:
    """Levelled vicinal surface: monatomic steps of a miscut crystal, as after plane fitting.

    The steps are the level lines of ``φ(x, y) + m·f(x, y)``, where φ is a
    ramp that rises by an integer number of terraces across the periodic map
    (about one per ``width_px``, perpendicular to ``direction_deg``) and ``f``
    a smooth random field (correlation two terrace widths) that makes the
    steps meander. Heights are ``step · (⌊φ + m f⌋ − φ)``: flat-topped
    terraces with the mean miscut plane removed, periodic by construction.
    """
    rows, cols = shape
    theta = math.radians(direction_deg)
    n_x = round(cols / width_px * math.cos(theta))
    n_y = round(rows / width_px * math.sin(theta))
    if n_x == 0 and n_y == 0:
        n_x = 1
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ramp = n_x * xx / cols + n_y * yy / rows
    levels = np.floor(ramp + meander * gaussian_field(shape, 2.0 * width_px, rng))
    out: FloatArray = step_nm * (levels - ramp)
    return out


def _load_with_afmdrift_io(path: Path) -> tuple[FloatArray, tuple[float, float] | None]:
    """Read a height image with the project's readers (imported lazily)."""

    try:
        image = load_image(path)
    except (OSError, ValueError) as err:
        raise ConfigError(f"sample.texture.path = {str(path)!r}: cannot read: {err}") from None
    pixel = image.pixel_size_nm
    _log.info("texture %s: %s px, pixel size %s nm", path, image.heights_nm.shape, pixel)
    return image.heights_nm, (float(pixel[0]), float(pixel[1]))

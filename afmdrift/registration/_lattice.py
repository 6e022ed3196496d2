"""Lattice translations: which of the shifts a periodic sample allows is the drift.

On a periodic sample (a grating, a crystal lattice, the real NanoScope frame
with its period of about 10 px) the whole-image correlation has near-equal
peaks at every lattice translation of the true shift, and which one is the
highest says little: on crops of a perfect lattice the edges of the frame
decide it. This module decides between the translations by the content of
the two frames, with a statistical test whose significance holds on noisy
data, and says so when the content cannot decide.

Steps (:func:`decide`):

1. **Lattice vectors** (:func:`repeat_vectors`): the offsets at which the
   reference repeats itself, local maxima of its normalised autocorrelation
   (without wrap-around) of at least :data:`REPEAT_AC_MIN` that stand out
   of a dip on the way from the origin, to a fraction of a pixel (a
   parabola through each maximum).
2. **Candidates**: the highest correlation peak and its translations by the
   shortest lattice vectors, other correlation peaks that are lattice
   translations of it, and the translations nearest the prior (or nearest
   zero, so that a refusal names them).
3. **Residuals** (:class:`Residuals`): for each candidate, the reference
   minus the current frame moved back by it, the sub-pixel part by a Fourier
   shift of a mirrored cut-out (all-pass: it keeps the noise variance, which
   an interpolation would lower for some fractions and not others), refined
   by two Gauss-Newton steps to the least-squares shift. Each candidate thus
   gets its best fit: an integer shift alone would leave up to 0.7 px of
   misalignment, whose residual on a 10 px lattice is as large as the
   difference between two lattice translations.
4. **Paired test** (:func:`paired_test`): over the overlap two candidates
   share, cut into tiles of :data:`TILE_PX` (larger than the residuals'
   correlation length, so tiles are nearly independent), each tile levelled
   line by line and given its own least-squares shift within a fraction of
   a pixel (:func:`_tile_misfit`), the difference of their mean squared
   residuals per tile; tiles neither candidate fits (a changed area: above
   the tiles' noise floor, found from their lower quantiles,
   :func:`_fit_limit`) are left out; a t test and a sign test of the
   differences. On a perfect lattice with noise (both candidates equally
   right) the statistics stay within ±3.1 (960
   comparisons of SNR 5–10 pairs: cropped, circular, with line-correlated
   noise); the right translation of the real NanoScope frame beats its
   lattice neighbours at 11–26, a dot lattice with a tenth of its dots
   missing at 6.5–9.7 (numbers in ``docs/registration.md``).
5. **Decision**: the best candidate must beat every other by
   :data:`WIN_Z` and by :data:`WIN_EFFECT` of the signal variance, and its
   own lattice neighbours too (the search steps to a better neighbour until
   none is). Candidates it does not beat are tied; among tied ones a prior
   (the given or predicted drift) decides when one is nearer it by
   :data:`PRIOR_MARGIN_PX`; otherwise the decision is *ambiguous* and names
   the tied shifts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import scipy.fft as sfft

__all__ = [
    "BOUND_SLACK_PX",
    "PRIOR_MARGIN_PX",
    "REPEAT_AC_MIN",
    "TILE_PX",
    "WIN_EFFECT",
    "WIN_Z",
    "LatticeDecision",
    "Residuals",
    "decide",
    "local_peaks",
    "paired_test",
    "repeat_vectors",
    "within_bound",
]

F64 = npt.NDArray[np.float64]
Shift = tuple[float, float]

#: Smallest normalised autocorrelation of the reference at a lattice vector.
REPEAT_AC_MIN = 0.5
#: ... and how far it must rise above the lowest autocorrelation on the way
#: from the origin to it.
REPEAT_DIP = 0.3
#: Largest edge of the central part of a reference searched for a lattice (px).
REPEAT_PROBE_PX = 256
#: Shortest lattice vectors whose translations are candidates (± each).
NEIGHBOUR_VECTORS = 8
#: Smallest statistic (normal deviate) of the paired test by which a candidate
#: beats another.
WIN_Z = 4.0
#: ... and smallest mean difference of squared residuals, relative to the
#: signal variance (noise-free perfect lattices differ by 1e-4 of it, from
#: the sub-pixel shifts alone).
WIN_EFFECT = 2e-3
#: A prior decides between tied candidates when the nearest is nearer by this (px).
PRIOR_MARGIN_PX = 2.0
#: A shift counts as within a stated bound up to this much beyond it (px): a
#: bound is stated in whole pixels, a shift measured to a fraction.
BOUND_SLACK_PX = 0.5
#: Edge of the tiles whose mean squared residuals the paired test compares
#: (px): larger than the residuals' correlation length on the textures tried
#: (a 10-px lattice, particles), small enough for 80–150 tiles per frame.
TILE_PX = 16
#: Tiles whose better fit is more than this many deviations above the noise
#: floor of the tiles (:func:`_fit_limit`) are changed content, and left out
#: of the paired test.
CHANGED_MAD = 5.0
#: Quantiles of the tiles' better fits to which the noise floor's normal is
#: fitted: low ones, which changed tiles (only ever worse fits) do not reach.
FLOOR_QUANTILES = (0.1, 0.3)
#: Fewest tiles the paired test needs to decide anything.
MIN_TILES = 16
#: Margin (px) of the cut-outs that are Fourier-shifted, and of the overlap.
MARGIN_PX = 4
#: Largest edge of the region the residuals are compared on (px, centred):
#: 64 tiles are plenty, and larger frames would only cost time.
MAX_REGION_PX = 256
#: Largest edge of the region each candidate's shift is refined on (px).
REFINE_REGION_PX = 128
#: Rounds of stepping to a better lattice neighbour.
MAX_ROUNDS = 4
#: Candidates within this distance (px) after refinement are one.
SAME_PX = 1.0


def _parabola(m: float, z: float, p: float) -> float:
    den = m - 2.0 * z + p
    return 0.0 if den >= 0 else float(np.clip(0.5 * (m - p) / den, -0.5, 0.5))


def subpixel_peak(surface: F64, dx: int, dy: int) -> Shift:
    """``(dx, dy)`` moved to the vertex of a parabola through the maximum of
    the circular ``surface`` at that integer offset and its neighbours along
    each axis (within ±0.5 px)."""
    rows, cols = surface.shape
    r, c = dy % rows, dx % cols
    z = float(surface[r, c])
    fx = _parabola(float(surface[r, (c - 1) % cols]), z, float(surface[r, (c + 1) % cols]))
    fy = _parabola(float(surface[(r - 1) % rows, c]), z, float(surface[(r + 1) % rows, c]))
    return dx + fx, dy + fy


def local_peaks(surface: F64, floor: float) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Rows and columns of the circular 3×3 local maxima of ``surface`` at or
    above ``floor``, highest first."""
    peak = surface >= floor
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= surface >= np.roll(surface, (dr, dc), axis=(0, 1))
    rows, cols = np.nonzero(peak)
    order = np.argsort(-surface[rows, cols], kind="stable")
    return rows[order], cols[order]


def _autocorrelation(image: F64) -> F64:
    """Normalised autocorrelation of ``image`` without wrap-around: at each
    offset the Pearson correlation of the image with itself moved by it, over
    their overlap (zero-padded FFTs; element ``[dy mod 2R, dx mod 2C]``)."""
    rows, cols = image.shape
    shape = (2 * rows, 2 * cols)
    a = image - image.mean()
    # the transforms of the three images the correlations pair, each made once
    f_ones, f_a, f_aa = (sfft.rfft2(x, s=shape) for x in (np.ones_like(a), a, a * a))

    def corr(fx: npt.NDArray[np.complex128], fy: npt.NDArray[np.complex128]) -> F64:
        out: F64 = sfft.irfft2(np.conj(fx) * fy, s=shape)
        return out

    n = np.maximum(np.round(corr(f_ones, f_ones)), 1.0)
    s_fixed, s_moved = corr(f_a, f_ones), corr(f_ones, f_a)
    q_fixed, q_moved = corr(f_aa, f_ones), corr(f_ones, f_aa)
    var_fixed = np.maximum(q_fixed - s_fixed**2 / n, 0.0)
    var_moved = np.maximum(q_moved - s_moved**2 / n, 0.0)
    den = np.sqrt(var_fixed * var_moved)
    out: F64 = np.zeros(shape)
    ok = den > 1e-12 * float(den.max())
    np.divide(corr(f_a, f_a) - s_fixed * s_moved / n, den, out=out, where=ok)
    return out


def repeat_vectors(image: F64) -> F64:
    """Lattice vectors of ``image``: offsets ``(dx, dy)`` px (sub-pixel) at
    which it repeats itself, shortest first; shape ``(k, 2)``, empty when it
    does not (a rough or particle texture, whose autocorrelation falls off
    from the origin).

    An offset ``v`` repeats the image when its autocorrelation
    (:func:`_autocorrelation`, of the central :data:`REPEAT_PROBE_PX` at
    most) has a local maximum of at least :data:`REPEAT_AC_MIN` there that
    stands :data:`REPEAT_DIP` above the lowest value on the way from the
    origin (a lattice falls to zero or below between its repeats, whereas a
    smooth texture's autocorrelation only wanders), and reaches
    :data:`REPEAT_AC_MIN` again at ``2v`` (a lattice repeats again; a chance
    alignment of a few particles does not). ``2v`` must lie within a third
    of the probe, where the overlap stays large: lattice vectors up to 42 px
    are found, beyond what the block search could confuse."""
    rows, cols = image.shape
    r0, c0 = max(0, (rows - REPEAT_PROBE_PX) // 2), max(0, (cols - REPEAT_PROBE_PX) // 2)
    probe = image[r0 : r0 + REPEAT_PROBE_PX, c0 : c0 + REPEAT_PROBE_PX]
    if float(probe.std()) == 0.0:
        return np.zeros((0, 2))
    ac = _autocorrelation(probe)
    n_rows, n_cols = ac.shape
    p_rows, p_cols = probe.shape
    out = []
    for r, c in zip(*local_peaks(ac, REPEAT_AC_MIN), strict=True):
        dy = int(r) - n_rows if r >= n_rows // 2 else int(r)
        dx = int(c) - n_cols if c >= n_cols // 2 else int(c)
        if (dx, dy) == (0, 0) or 6 * abs(dy) > p_rows or 6 * abs(dx) > p_cols:
            continue
        steps = np.linspace(0.0, 1.0, 2 * max(abs(dx), abs(dy)) + 1)[1:-1]
        way = ac[
            np.round(steps * dy).astype(int) % n_rows, np.round(steps * dx).astype(int) % n_cols
        ]
        dips = way.size > 0 and float(way.min()) <= float(ac[r, c]) - REPEAT_DIP
        # a lattice repeats again at twice the vector (within a pixel)
        twice = ac[
            np.ix_((2 * dy + np.arange(-1, 2)) % n_rows, (2 * dx + np.arange(-1, 2)) % n_cols)
        ]
        if dips and float(twice.max()) >= REPEAT_AC_MIN:
            out.append(subpixel_peak(ac, dx, dy))
    if not out:
        return np.zeros((0, 2))
    vecs = np.array(out)
    return vecs[np.argsort(np.hypot(vecs[:, 0], vecs[:, 1]), kind="stable")]


Region = tuple[int, int, int, int]  # y0, y1, x0, x1 in reference coordinates


class Residuals:
    """Residuals of the reference ``a`` against the current frame ``b`` moved
    back by candidate shifts (``b(u + d) = a(u)``), both levelled height
    images of one shape. Each candidate is refined once (:meth:`refine`) and
    moved once over its own overlap; a pair of candidates is compared on the
    part of the reference both keep (:meth:`pair`)."""

    def __init__(self, a: F64, b: F64) -> None:
        self.a, self.b = a, b
        self._refined: dict[Shift, Shift | None] = {}
        self._moved: dict[Shift, tuple[Region, F64, F64, F64]] = {}

    def region(self, shift: Shift, *, limit: int = MAX_REGION_PX) -> Region | None:
        """The part of the reference that ``shift`` keeps inside the current
        frame (with :data:`MARGIN_PX`, and 2 px for the refinement), centred
        and at most ``limit`` per axis; None when under :data:`TILE_PX`."""
        rows, cols = self.a.shape
        m = MARGIN_PX + 2
        ix, iy = round(shift[0]), round(shift[1])
        y0, y1 = max(m, m - iy), min(rows - m, rows - m - iy)
        x0, x1 = max(m, m - ix), min(cols - m, cols - m - ix)
        if min(y1 - y0, x1 - x0) < TILE_PX:
            return None
        if y1 - y0 > limit:
            y0 = (y0 + y1) // 2 - limit // 2
            y1 = y0 + limit
        if x1 - x0 > limit:
            x0 = (x0 + x1) // 2 - limit // 2
            x1 = x0 + limit
        return y0, y1, x0, x1

    def _spectrum(self, region: Region, base: tuple[int, int]) -> npt.NDArray[np.complex128]:
        """Spectrum of the cut-out of ``b`` at ``region + base`` (with
        :data:`MARGIN_PX`), mirrored on both axes: a continuous periodic
        extension, so a Fourier shift of it rings only where the slope jumps."""
        y0, y1, x0, x1 = region
        m = MARGIN_PX
        bx, by = base
        cut = self.b[y0 + by - m : y1 + by + m, x0 + bx - m : x1 + bx + m]
        mirrored = np.block([[cut, cut[:, ::-1]], [cut[::-1], cut[::-1, ::-1]]])
        spec: npt.NDArray[np.complex128] = sfft.rfft2(mirrored)
        return spec

    @staticmethod
    def _shifted(
        spec: npt.NDArray[np.complex128], region: Region, rest: Shift, *, gradient: bool
    ) -> tuple[F64, F64 | None, F64 | None]:
        """The mirrored cut-out of :meth:`_spectrum` moved by ``rest`` px
        (``v(u) = cut(u + rest)``) over ``region``, with its x and y
        derivatives."""
        y0, y1, x0, x1 = region
        shape = (spec.shape[0], 2 * (spec.shape[1] - 1))
        ky = sfft.fftfreq(shape[0])[:, None]
        kx = sfft.rfftfreq(shape[1])[None, :]
        moved = spec * np.exp(2j * np.pi * (kx * rest[0] + ky * rest[1]))
        inner = (slice(MARGIN_PX, MARGIN_PX + y1 - y0), slice(MARGIN_PX, MARGIN_PX + x1 - x0))
        value: F64 = sfft.irfft2(moved, s=shape)[inner]
        if not gradient:
            return value, None, None
        gx: F64 = sfft.irfft2(moved * (2j * np.pi * kx), s=shape)[inner]
        gy: F64 = sfft.irfft2(moved * (2j * np.pi * ky), s=shape)[inner]
        return value, gx, gy

    def refine(self, shift: Shift) -> Shift | None:
        """The least-squares shift near ``shift``: two Gauss-Newton steps (each
        at most 1 px, in all at most 2 px) on the central part
        (:data:`REFINE_REGION_PX`) of its overlap; None when the overlap is
        too small."""
        key = (float(shift[0]), float(shift[1]))
        if key in self._refined:
            return self._refined[key]
        region = self.region(key, limit=REFINE_REGION_PX)
        if region is None or self.region(key) is None:
            self._refined[key] = None
            return None
        base = (round(key[0]), round(key[1]))
        spec = self._spectrum(region, base)
        y0, y1, x0, x1 = region
        a = self.a[y0:y1, x0:x1]
        yy, xx = np.mgrid[: y1 - y0, : x1 - x0].astype(np.float64)
        plane, _ = np.linalg.qr(np.column_stack([np.ones(xx.size), xx.ravel(), yy.ravel()]))

        def flat(z: F64) -> F64:
            """``z`` (raveled) without its least-squares plane (a tilt or z
            offset between the frames is not a shift)."""
            r = z.ravel()
            out: F64 = r - plane @ (plane.T @ r)
            return out

        s = key
        for _ in range(2):
            v, gx, gy = self._shifted(spec, region, (s[0] - base[0], s[1] - base[1]), gradient=True)
            assert gx is not None
            assert gy is not None
            e = flat(a - v)
            jac = np.stack([flat(gx), flat(gy)], axis=1)
            # a − b(u + s + δ) ≈ e − J δ
            step, *_ = np.linalg.lstsq(jac, e, rcond=None)
            step = np.clip(step, -1.0, 1.0)
            s = (
                float(np.clip(s[0] + step[0], base[0] - 2, base[0] + 2)),
                float(np.clip(s[1] + step[1], base[1] - 2, base[1] + 2)),
            )
        self._refined[key] = s
        return s

    def moved(self, shift: Shift) -> tuple[Region, F64, F64, F64]:
        """``b(u + shift)`` over the shift's overlap (:meth:`region`), and its
        x and y derivatives, for a shift :meth:`refine` returned."""
        if shift not in self._moved:
            region = self.region(shift)
            assert region is not None
            base = (round(shift[0]), round(shift[1]))
            rest = (shift[0] - base[0], shift[1] - base[1])
            value, gx, gy = self._shifted(self._spectrum(region, base), region, rest, gradient=True)
            assert gx is not None
            assert gy is not None
            self._moved[shift] = (region, value, gx, gy)
        return self._moved[shift]

    def pair(self, x: Shift, y: Shift) -> Pair | None:
        """The residuals of ``x`` and ``y`` over the part of the reference
        both keep (:class:`Pair`); None when smaller than :data:`TILE_PX`."""
        mx, my = self.moved(x), self.moved(y)
        rx, ry = mx[0], my[0]
        y0, y1 = max(rx[0], ry[0]), min(rx[1], ry[1])
        x0, x1 = max(rx[2], ry[2]), min(rx[3], ry[3])
        if min(y1 - y0, x1 - x0) < TILE_PX:
            return None
        a = self.a[y0:y1, x0:x1]
        parts = []
        for (r0, _, c0, _), *arrays in (mx, my):
            value, gx, gy = (z[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0] for z in arrays)
            parts.append((a - value, gx, gy))
        bx = (round(x[1]), round(x[0]))
        b = self.b[y0 + bx[0] : y1 + bx[0], x0 + bx[1] : x1 + bx[1]]
        scale = 0.5 * (float(a.var()) + float(b.var()))
        return Pair(*parts[0], *parts[1], scale)


class Pair(NamedTuple):
    """Two candidates' residuals over their common overlap, with the current
    frame's x and y derivatives there (moved by each), and the overlap's
    signal variance (the mean of the two frames')."""

    residual: F64
    gx: F64
    gy: F64
    other_residual: F64
    other_gx: F64
    other_gy: F64
    signal_var: float

    def swapped(self) -> Pair:
        """The same pair, the other candidate first."""
        return Pair(*self[3:6], *self[:3], self.signal_var)


@dataclass(frozen=True)
class PairedTest:
    """:func:`paired_test` of a candidate against another."""

    t: float
    """t statistic of the tile differences ``mse_other − mse_best`` (positive:
    the first candidate fits better)."""
    sign_z: float
    """Sign test of the same differences, as a normal deviate."""
    effect: float
    """Mean tile difference over the signal variance of the overlap."""
    median_effect: float
    """Median tile difference over the signal variance."""
    tiles: int

    @property
    def z(self) -> float:
        """The stronger of the two tests."""
        return max(self.t, self.sign_z)

    @property
    def wins(self) -> bool:
        """The first candidate is clearly the better one: by the t test with
        its mean difference, or by the sign test with its median one."""
        if self.tiles < MIN_TILES:
            return False
        by_t = self.t >= WIN_Z and self.effect >= WIN_EFFECT
        return by_t or (self.sign_z >= WIN_Z and self.median_effect >= WIN_EFFECT)


#: The test of a pair without enough common overlap: no decision.
NO_TEST = PairedTest(0.0, 0.0, 0.0, 0.0, 0)


def paired_test(pair: Pair) -> PairedTest:
    """Paired test of two candidates' residuals over their common overlap.

    The per-pixel differences of squared residuals are correlated over the
    texture's features, so the comparison is made per tile of
    :data:`TILE_PX`: in each tile both residuals are levelled line by line
    (the frames' scan-line offsets and tilts are not shifts, and line noise
    correlates along a whole row of tiles otherwise) and their mean squares
    compared. Tiles that neither candidate fits (:data:`CHANGED_MAD`) are
    left out. Two tests of the tile differences, each valid on its own, are
    made: a t test (strong when most tiles differ a little) and a sign test
    (strong when a changed area makes a few tiles differ wildly either way).
    """
    rows, cols = pair.residual.shape
    tile = TILE_PX
    nr, nc = rows // tile, cols // tile
    if nr * nc < 2:
        return NO_TEST
    mse_best, mse_other = (
        _tile_misfit(e, gx, gy, tile, nr, nc) for e, gx, gy in (pair[:3], pair[3:6])
    )
    # Tiles that neither candidate fits (a changed area: a moved or new
    # particle, a scratch) are left out, whichever is right: there the
    # difference of two large residuals is noise that would swamp the rest.
    fit = np.minimum(mse_best, mse_other)
    diff = (mse_other - mse_best)[fit <= _fit_limit(fit)]
    n = int(diff.size)
    if n < 2:
        return NO_TEST
    mean = float(diff.mean())
    sd = float(diff.std(ddof=1))
    if sd > 0:
        t = mean / (sd / math.sqrt(n))
    else:
        t = math.inf if mean > 0 else (-math.inf if mean < 0 else 0.0)
    nonzero = int(np.count_nonzero(diff))
    sign_z = (
        (2.0 * int(np.count_nonzero(diff > 0)) - nonzero) / math.sqrt(nonzero) if nonzero else 0.0
    )
    scale = 1.0 / pair.signal_var if pair.signal_var > 0 else 0.0
    return PairedTest(t, sign_z, mean * scale, float(np.median(diff)) * scale, n)


def _fit_limit(fit: F64) -> float:
    """Largest tile misfit ``fit`` (the better candidate's, per tile) that
    still counts as a fit: :data:`CHANGED_MAD` deviations above the noise
    floor of the tiles, a normal fitted to their :data:`FLOOR_QUANTILES`.

    A change between the frames only ever raises a tile's misfit, so the
    changed tiles (a tenth to a third of them when 12–25 % of the frame is
    changed, for a change touches every tile it crosses) sit in the upper
    tail, and the lower quantiles keep to the floor. On a lattice a changed
    tile is fitted moderately by a candidate a period off, whose shift moves
    the tile onto unchanged lattice elsewhere; a median and MAD of all tiles
    would take those fits into the floor and its spread, and keep these
    tiles, each a vote against the right candidate. The limit depends on the better
    fit alone, whichever candidate gives it, so it keeps the tests'
    symmetry under the null (two candidates equally right)."""
    lo, hi = (float(q) for q in np.quantile(fit, FLOOR_QUANTILES))
    z_lo, z_hi = (NormalDist().inv_cdf(q) for q in FLOOR_QUANTILES)
    spread = (hi - lo) / (z_hi - z_lo)
    centre = hi - z_hi * spread
    return centre + CHANGED_MAD * max(spread, 0.01 * centre)


def _tile_misfit(e: F64, gx: F64, gy: F64, tile: int, nr: int, nc: int) -> F64:
    """Mean square of the residual ``e`` in each of ``nr × nc`` tiles, after
    line levelling (:func:`_tiles_levelled`) and the tile's own least-squares
    shift (within the linear range, a fraction of a pixel: ``e − gx·δx −
    gy·δy``, with the current frame's derivatives): two scans of a sample
    differ by local shifts of a fraction of a pixel (creep, scan
    nonlinearity), which a lattice translation a period off cannot make
    good, but which otherwise decide the tiles by chance."""
    et, xt, yt = (_tiles_levelled(z, tile, nr, nc) for z in (e, gx, gy))
    jac = np.stack([xt, yt], axis=2)  # (tiles, pixels, 2)
    normal = np.einsum("tpi,tpj->tij", jac, jac) + 1e-12 * np.eye(2)
    rhs = np.einsum("tpi,tp->ti", jac, et)
    step = np.linalg.solve(normal, rhs[..., None])[..., 0]
    out: F64 = ((et - np.einsum("tpi,ti->tp", jac, step)) ** 2).mean(axis=1)
    return out


def _tiles_levelled(e: F64, tile: int, nr: int, nc: int) -> F64:
    """``e`` cut into ``nr × nc`` tiles (rows of the result, raveled), each
    line of each tile without its mean and each tile without its slope along
    x: the frames' scan-line offsets, a tilt or a z offset between them
    (which a manipulated AFM frame gets) are not shifts, and line noise would
    make the tiles of one row agree by chance."""
    tiles = e[: nr * tile, : nc * tile].reshape(nr, tile, nc, tile).transpose(0, 2, 1, 3)
    tiles = tiles - tiles.mean(axis=3, keepdims=True)
    x = np.arange(tile) - (tile - 1) / 2.0
    slope = (tiles * x).sum(axis=(2, 3), keepdims=True) / (tile * float(x @ x))
    out: F64 = (tiles - slope * x).reshape(nr * nc, tile * tile)
    return out


@dataclass(frozen=True)
class LatticeDecision:
    """Outcome of :func:`decide`."""

    shift: Shift | None
    """The chosen shift (sub-pixel), or None when the decision is ambiguous."""
    tied: tuple[Shift, ...]
    """The candidates the content cannot tell from the best (the chosen one
    first when there is one), nearest the prior (or zero) first."""
    by: str
    """``content`` (it beat every other candidate), ``bound`` (tied, the only
    one within the stated bound), ``equivalent`` (tied, the one nearest the
    prior or zero, as asked), ``prior`` (tied, the prior decided),
    ``ambiguous`` (tied, nothing decides) or ``outside`` (tied, none within
    the stated bound)."""
    t: float
    """Smallest t of the best candidate against the others (inf: no other)."""


def _translations(start: Shift, vectors: F64, target: Shift, count: int) -> list[Shift]:
    """The ``count`` translations of ``start`` by integer combinations of the
    two shortest non-collinear ``vectors`` nearest ``target``."""
    v1 = vectors[0]
    basis = [v1]
    for v in vectors[1:]:
        cross = abs(v1[0] * v[1] - v1[1] * v[0])
        if cross > 0.25 * float(np.hypot(*v1)) * float(np.hypot(*v)):
            basis.append(v)
            break
    mat = np.array(basis).T  # 2 × k
    coef, *_ = np.linalg.lstsq(mat, np.subtract(target, start), rcond=None)
    centre = np.round(coef).astype(int)
    offsets = [np.array(o) for o in np.ndindex(*([5] * len(basis)))]
    out = []
    for o in offsets:
        n = centre + o - 2
        p = np.asarray(start) + mat @ n
        out.append((float(p[0]), float(p[1])))
    out.sort(key=lambda p: math.hypot(p[0] - target[0], p[1] - target[1]))
    return out[:count]


def decide(
    a: F64,
    b: F64,
    *,
    start: Shift,
    peaks: list[Shift],
    vectors: F64,
    prior_px: Shift | None,
    bound_px: float | None = None,
    equivalent: bool = False,
) -> LatticeDecision:
    """Decide between the lattice translations of ``start`` (the highest
    correlation peak) for ``b(u + d) = a(u)``.

    Parameters
    ----------
    a, b : ndarray, shape (rows, cols)
        Levelled reference and current heights.
    start : (float, float)
        The highest correlation peak, px (sub-pixel).
    peaks : list of (float, float)
        Other correlation peaks that are lattice translations of it.
    vectors : ndarray, shape (k, 2)
        The reference's lattice vectors (:func:`repeat_vectors`), k ≥ 1.
    prior_px : (float, float) or None
        The expected drift, if one is known (given or predicted).
    bound_px : float or None
        The largest drift the user states is possible (px, per axis, from
        zero; ``RegistrationConfig.max_shift_px``): tied translations beyond
        it are excluded, so one alone within it is taken (``by == "bound"``)
        and none within it is ``"outside"`` (refused).
    equivalent : bool
        The user wants the frames registered, not the drift tracked
        (``RegistrationConfig.lattice == "equivalent"``): among translations
        still tied, the one nearest the prior (or zero) is taken
        (``by == "equivalent"``) instead of a refusal.

    Returns
    -------
    LatticeDecision
    """
    res = Residuals(a, b)
    short = vectors[:NEIGHBOUR_VECTORS]
    target = prior_px if prior_px is not None else (0.0, 0.0)
    seeds = [start, *peaks]
    seeds += [(start[0] + v[0], start[1] + v[1]) for v in short]
    seeds += _translations(start, vectors, target, 4)
    if bound_px is not None and prior_px is not None:
        seeds += _translations(start, vectors, (0.0, 0.0), 4)
    cands: list[Shift] = []
    for s in seeds:
        _add(cands, res.refine(s))
    if not cands:
        return LatticeDecision(None, (), "ambiguous", 0.0)
    tests: dict[tuple[Shift, Shift], PairedTest] = {}

    def test(x: Shift, y: Shift) -> PairedTest:
        """x against y, on their common overlap."""
        if (x, y) not in tests:
            both = res.pair(x, y)
            tests[(x, y)] = NO_TEST if both is None else paired_test(both)
        return tests[(x, y)]

    best = cands[0]
    for _ in range(MAX_ROUNDS):
        # step to any candidate that beats the best, then add its neighbours
        better = [c for c in cands if c != best and test(c, best).wins]
        if better:
            best = max(better, key=lambda c: test(c, best).z)
        size = len(cands)
        for v in short:
            _add(cands, res.refine((best[0] + v[0], best[1] + v[1])))
        if not better and len(cands) == size:
            break

    def dist(s: Shift) -> float:
        return math.hypot(s[0] - target[0], s[1] - target[1])

    tied = [best] + [c for c in cands if c != best and not test(best, c).wins]
    if len(tied) > 1:
        # A tie: name the tied translation nearest the prior (or zero) with its
        # lattice neighbours, and take the nearest from that full set; with a
        # bound, the translations nearest zero too (the bound is about zero).
        nearest = min(tied, key=dist)
        near_zero = min(tied, key=lambda s: max(abs(s[0]), abs(s[1])))
        for centre in {nearest, near_zero} if bound_px is not None else {nearest}:
            for v in short:
                _add(cands, res.refine((centre[0] + v[0], centre[1] + v[1])))
        tied = [best] + [c for c in cands if c != best and not test(best, c).wins]
    t_min = min((test(best, c).z for c in cands if c != best), default=math.inf)

    if len(tied) == 1:
        return LatticeDecision(best, (best,), "content", t_min)
    tied.sort(key=dist)
    if bound_px is not None:
        inside = [s for s in tied if within_bound(s, bound_px)]
        if not inside:
            return LatticeDecision(None, tuple(tied), "outside", t_min)
        if len(inside) == 1:
            return LatticeDecision(inside[0], tuple(tied), "bound", t_min)
        tied = inside
    if equivalent:
        return LatticeDecision(tied[0], tuple(tied), "equivalent", t_min)
    if prior_px is not None and dist(tied[1]) - dist(tied[0]) >= PRIOR_MARGIN_PX:
        return LatticeDecision(tied[0], tuple(tied), "prior", t_min)
    return LatticeDecision(None, tuple(tied), "ambiguous", t_min)


def within_bound(shift: Shift, bound_px: float) -> bool:
    """Whether ``shift`` lies within the stated bound on the drift: at most
    ``bound_px`` from zero on each axis, with :data:`BOUND_SLACK_PX` for the
    sub-pixel part (a bound is stated in whole pixels; a shift of 7.3 px is
    "7 px")."""
    return max(abs(shift[0]), abs(shift[1])) <= bound_px + BOUND_SLACK_PX


def _add(cands: list[Shift], shift: Shift | None) -> None:
    """Append ``shift`` unless None or within :data:`SAME_PX` of a candidate."""
    if shift is None:
        return
    for c in cands:
        if math.hypot(c[0] - shift[0], c[1] - shift[1]) < SAME_PX:
            return
    cands.append(shift)

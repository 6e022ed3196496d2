"""Whole-frame coarse alignment: the integer prior of the block search.

When no expected drift is known, one phase correlation of the two whole
height images gives the integer shift; the block windows are then moved by
it, so the block stage only has to resolve a small residual. That both
widens the measurable range beyond the block search radius and keeps the
window-induced bias of large in-window shifts away.

The shift is a peak of the phase correlation of the two images with their
per-line medians removed (line levelling, which takes out the line-to-line
offsets of AFM scans), without a window. It is used only when two checks
agree (:attr:`CoarseShift.trusted`): the peak stands out of its correlation
surface, and the x-gradient images (eq. 2 of Yang et al. 2008, what the
block engine sees) also correlate at that shift. On the real NanoScope pair
(a lattice with a period of about 10 px, true shift about (0, 28) px) this
gives (0, 28); the previous method (2×2-binned gradient images under a
raised-cosine window) gave (2, 18), a wrong lattice peak, and a Hann window
on the heights moved the peak to 18 px as well.

Three things make a correlation peak lie, and each has its own step here:

* **Wrap-around.** A circular correlation cannot tell a shift ``d`` from
  ``d − N``: 350 px of a 450 px image and −100 px give the same peak. Each
  alternative is scored by the evidence of its overlap (at least
  :data:`MIN_OVERLAP_PX` per axis): the normalised cross-correlation of the
  levelled images there, times the square root of the overlap's share of
  the frame (the NCC of a thin strip is as high by chance as that of the
  whole frame is with half its content changed), and the best is kept.
* **Lattices.** On a periodic sample (graphite, a grating) the correlation
  has near-equal peaks at every lattice translation. Peaks of at least
  :data:`LATTICE_PEAK_RATIO` of the highest, at offsets from it where the
  reference repeats itself (a local maximum of its autocorrelation of at
  least :data:`LATTICE_AC_MIN`), are compared by the content
  itself: the mean squared difference of the levelled images over the
  overlap (normalised by their variance). Peaks whose difference is within
  :data:`LATTICE_MSE_RATIO` (and :data:`LATTICE_MSE_FLOOR`) of the best
  cannot be told apart by any method that compares the two images; the one
  nearest the prior (the predicted drift, or zero) is taken,
  :attr:`CoarseShift.lattice_px` lists the others' offsets, and
  :attr:`CoarseShift.ambiguous` says when two were equally near the prior
  (then no choice is defensible). On the real NanoScope pair the second
  peak, 0.89 of the first, differs in content (its difference is several
  times larger) and is dropped.
* **Static structure.** A fixed mask, a border or an artefact burnt into both
  frames correlates perfectly at zero shift. Patches of pixels with exactly
  the same height in both frames are *static*; when they are present
  (but not everywhere: identical frames are simply not moved), the
  correlation is the masked normalised cross-correlation of Padfield
  (IEEE TIP 21(5), 2012) over the other pixels, zero-padded so that no shift
  wraps, and the peak is taken where at least :data:`MASKED_MIN_OVERLAP` of
  the pixels overlap.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = [
    "COARSE_MIN_GRADIENT_Z",
    "COARSE_MIN_Z",
    "CoarseShift",
    "coarse_shift",
    "overlap_slices",
    "static_pixels",
]

#: Smallest coarse correlation peak (in standard deviations of the surface) that is used.
COARSE_MIN_Z = 6.0
#: Smallest x-gradient correlation at the coarse shift (one location, so 3 sigma suffices).
COARSE_MIN_GRADIENT_Z = 3.0
#: Peaks at least this fraction of the highest are lattice candidates.
LATTICE_PEAK_RATIO = 0.7
#: Smallest normalised autocorrelation of the reference at a lattice vector.
LATTICE_AC_MIN = 0.5
#: Candidates whose normalised difference is within this factor of the best (and
#: :data:`LATTICE_MSE_FLOOR` above it) are indistinguishable by content.
LATTICE_MSE_RATIO = 1.1
LATTICE_MSE_FLOOR = 2e-3
#: Candidates compared by content (the nearest to the prior, and the highest).
LATTICE_CANDIDATES = 6
#: Smallest overlap (px per axis) at which a wrap-around alternative is scored.
MIN_OVERLAP_PX = 16
#: Margin by which a wrapped alternative's overlap score (:func:`_overlap_score`)
#: must beat the minimal-image shift's.
UNWRAP_MARGIN = 0.1
#: Masked correlation: smallest normalised correlation that is trusted.
MASKED_MIN_NCC = 0.5
#: Masked correlation: smallest share of the valid pixels that must overlap.
MASKED_MIN_OVERLAP = 0.1
#: Share of static pixels above which the frames are taken as identical rather
#: than as carrying static structure.
STATIC_IDENTICAL = 0.9
#: Smallest share of static pixels that is acted on.
STATIC_MIN = 1e-3
#: Edge of the smallest square patch of equal heights that counts as static.
STATIC_PATCH_PX = 5

F64 = npt.NDArray[np.float64]
BArr = npt.NDArray[np.bool_]


class CoarseShift(NamedTuple):
    """Result of :func:`coarse_shift`."""

    dx_px: float
    dy_px: float
    peak_z: float
    """Peak of the levelled-height correlation over its surface's standard deviation."""
    gradient_z: float
    """The x-gradient correlation at the same shift, in its surface's standard deviations."""
    lattice_px: tuple[tuple[float, float], ...] = ()
    """Offsets ``(dx, dy)`` from this shift to other shifts the images cannot tell
    apart (lattice translations of a periodic sample), shortest first."""
    ambiguous: bool = False
    """Two indistinguishable shifts were equally near the prior: no choice is defensible."""
    method: str = "phase"
    """``phase`` (phase correlation) or ``masked`` (static pixels left out)."""
    peak_ncc: float = math.nan
    """``masked``: the normalised cross-correlation at the shift (1: identical)."""

    @property
    def trusted(self) -> bool:
        """Both correlations agree that the shift is real, and it is not ambiguous.
        For the masked correlation, which is not whitened (its surface is broad,
        so a z-score says little), the correlation itself must reach
        :data:`MASKED_MIN_NCC` (true matches 0.70–0.95, unrelated frames with the
        same static border 0.13–0.15)."""
        if self.ambiguous:
            return False
        if self.method == "masked":
            return self.peak_ncc >= MASKED_MIN_NCC
        return self.peak_z >= COARSE_MIN_Z and self.gradient_z >= COARSE_MIN_GRADIENT_Z

    @property
    def prior_px(self) -> tuple[float, float]:
        """``(dx, dy)`` when trusted, else ``(0, 0)``."""
        return (self.dx_px, self.dy_px) if self.trusted else (0.0, 0.0)

    def search_limit_px(self) -> float | None:
        """Largest block search half-width that cannot reach the next lattice
        translation (None without a lattice)."""
        if not self.lattice_px:
            return None
        shortest = min(max(abs(a), abs(b)) for a, b in self.lattice_px)
        return max(1.0, math.ceil(shortest / 2) - 1)

    def describe(self) -> str:
        """One line for ``afmdrift measure`` and the result's ``prior``."""
        if self.method == "masked":
            text = f"masked correlation {self.peak_ncc:.2f} (static pixels left out)"
        else:
            text = f"{self.method} peak z={self.peak_z:.1f}, gradient z={self.gradient_z:.1f}"
        if self.lattice_px:
            vecs = ", ".join(f"({a:+g}, {b:+g})" for a, b in self.lattice_px[:4])
            text += f"; lattice: also {vecs} px, took the one nearest the prior"
        if self.ambiguous:
            text += "; ambiguous: two lattice translations equally near the prior"
        return text


def _phase_correlation(reference: F64, current: F64) -> F64:
    """Inverse FFT of ``F(cur)·conj(F(ref)) / |…|``: a peak at ``d`` for
    ``cur(u) = ref(u − d)``. The magnitude is floored at 1e-12 of its maximum
    (and at the smallest normal double), so the division is always finite."""
    cross = np.fft.rfft2(current) * np.conj(np.fft.rfft2(reference))
    mag = np.abs(cross)
    np.maximum(mag, float(mag.max()) * 1e-12 + np.finfo(np.float64).tiny, out=mag)
    cross /= mag
    corr: F64 = np.fft.irfft2(cross, s=reference.shape)
    return corr


def _z(corr: F64, r: int, c: int) -> float:
    spread = float(corr.std())
    return float(corr[r, c]) / spread if spread > 0 else 0.0


def _levelled(h: npt.NDArray[np.floating]) -> F64:
    g = np.asarray(h, dtype=np.float64)
    out: F64 = g - np.median(g, axis=1, keepdims=True)
    return out


def _gradient(h: npt.NDArray[np.floating]) -> F64:
    g: F64 = np.diff(np.asarray(h, dtype=np.float64), axis=1)
    g -= float(g.mean())
    return g


def static_pixels(
    reference: npt.NDArray[np.floating], current: npt.NDArray[np.floating]
) -> BArr | None:
    """Pixels that hold exactly the same height in both frames, in patches of at
    least :data:`STATIC_PATCH_PX` square (isolated coincidences of quantised
    heights are not structure).

    Returns the mask, or None when such pixels cover less than
    :data:`STATIC_MIN` of the frame, or :data:`STATIC_IDENTICAL` or more (the
    frames are the same image: zero shift is then the truth, not an
    artefact).
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    same = (np.asarray(reference, dtype=np.float32) == np.asarray(current, dtype=np.float32)).view(
        np.uint8
    )
    if not same.any():
        return None
    core = minimum_filter(same, size=STATIC_PATCH_PX, mode="constant", cval=0)
    mask: BArr = np.asarray(
        maximum_filter(core, size=STATIC_PATCH_PX, mode="constant", cval=0), dtype=bool
    )
    fraction = float(np.count_nonzero(mask)) / mask.size
    if not (STATIC_MIN <= fraction < STATIC_IDENTICAL):
        return None
    return mask


def _local_peaks(corr: F64, floor: float) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Rows and columns of the circular 3×3 local maxima of ``corr`` at or above
    ``floor``, highest first."""
    peak = corr >= floor
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= corr >= np.roll(corr, (dr, dc), axis=(0, 1))
    rows, cols = np.nonzero(peak)
    order = np.argsort(-corr[rows, cols], kind="stable")
    return rows[order], cols[order]


def overlap_slices(
    shape: tuple[int, ...], dx: int, dy: int
) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """``(rows, cols)`` slices of the reference and of the current frame that
    show the same sample for an integer shift ``(dx, dy)`` (a feature at u in
    the reference is at u + d in the current frame)."""
    rows, cols = shape[0], shape[1]
    ref = (slice(max(0, -dy), rows - max(0, dy)), slice(max(0, -dx), cols - max(0, dx)))
    cur = (slice(max(0, dy), rows - max(0, -dy)), slice(max(0, dx), cols - max(0, -dx)))
    return ref, cur


def _overlap(a: F64, b: F64, dx: int, dy: int) -> tuple[F64, F64] | None:
    """The parts of ``a`` (reference) and ``b`` (current) that show the same
    sample for ``b(u + d) = a(u)``, or None if smaller than MIN_OVERLAP_PX."""
    rows, cols = a.shape
    if abs(dx) > cols - MIN_OVERLAP_PX or abs(dy) > rows - MIN_OVERLAP_PX:
        return None
    ra, rb = overlap_slices(a.shape, dx, dy)
    return a[ra], b[rb]


def _ncc(a: F64, b: F64, dx: int, dy: int) -> float:
    """Normalised cross-correlation over the overlap at shift ``(dx, dy)``."""
    part = _overlap(a, b, dx, dy)
    if part is None:
        return -math.inf
    pa, pb = part
    pa = pa - pa.mean()
    pb = pb - pb.mean()
    den = math.sqrt(float(np.sum(pa * pa)) * float(np.sum(pb * pb)))
    return float(np.sum(pa * pb)) / den if den > 0 else -math.inf


def _difference(a: F64, b: F64, dx: int, dy: int) -> float:
    """Mean squared difference over the overlap (its mean removed), divided by
    the mean of the two parts' variances: 0 for identical content, about 2
    for unrelated content."""
    part = _overlap(a, b, dx, dy)
    if part is None:
        return math.inf
    pa, pb = part
    diff = pa - pb
    scale = 0.5 * (float(pa.var()) + float(pb.var()))
    return float(diff.var()) / scale if scale > 0 else math.inf


def _overlap_score(a: F64, b: F64, dx: int, dy: int) -> float:
    """Evidence that the overlap at shift ``(dx, dy)`` shows the same sample:
    its normalised cross-correlation times ``sqrt(overlap / frame)``.

    The NCC alone favours small overlaps: its chance value grows as the
    overlap shrinks, and a strip that happens to be unchanged correlates
    better than the whole frame does when a quarter of it was changed
    (manipulated frames whose content wraps around: a 22-row strip at
    ``d + N`` scored 0.95 against 0.7 at ``d`` and took every block window
    out of the frame). Weighted by the square root of its share, an NCC is
    on the scale of its significance (the NCC of ``n`` independent pixels
    has a chance spread of ``1/sqrt(n)``), so a thin strip must correlate
    far better than a large overlap to replace it."""
    rows, cols = a.shape
    share = (rows - abs(dy)) * (cols - abs(dx)) / (rows * cols)
    return _ncc(a, b, dx, dy) * math.sqrt(max(share, 0.0))


def _unwrap(a: F64, b: F64, dx: int, dy: int) -> tuple[int, int]:
    """The shift behind the circular peak at minimal-image shift ``(dx, dy)``:
    an alternative ``d ± N`` replaces it only when its overlap's evidence
    (:func:`_overlap_score`) is clearly larger (:data:`UNWRAP_MARGIN`); on a
    tie the larger overlap wins."""
    rows, cols = a.shape
    best, best_score = (dx, dy), _overlap_score(a, b, dx, dy)
    alt_x = [dx] + ([dx - cols] if dx > 0 else [dx + cols] if dx < 0 else [])
    alt_y = [dy] + ([dy - rows] if dy > 0 else [dy + rows] if dy < 0 else [])
    for ay in alt_y:
        for ax in alt_x:
            if (ax, ay) != (dx, dy):
                score = _overlap_score(a, b, ax, ay)
                if score > best_score + UNWRAP_MARGIN:
                    best, best_score = (ax, ay), score
    return best


def _masked_ncc(a: F64, b: F64, valid: BArr) -> F64:
    """Masked normalised cross-correlation (Padfield 2012) of ``b`` against
    ``a`` over the pixels ``valid`` in both, zero-padded (no wrap-around).
    Element ``[dy mod 2R, dx mod 2C]`` is the correlation at shift ``(dx, dy)``;
    shifts whose overlap has fewer than MASKED_MIN_OVERLAP of the valid pixels
    are 0."""
    rows, cols = a.shape
    shape = (2 * rows, 2 * cols)
    m = valid.astype(np.float64)
    fa, fb = a * m, b * m

    def spec(x: F64) -> npt.NDArray[np.complex128]:
        return np.fft.rfft2(x, s=shape)

    def corr(x: npt.NDArray[np.complex128], y: npt.NDArray[np.complex128]) -> F64:
        out: F64 = np.fft.irfft2(np.conj(x) * y, s=shape)
        return out

    sm, sa, sb = spec(m), spec(fa), spec(fb)
    n = np.maximum(np.round(corr(sm, sm)), 1.0)
    sum_a = corr(sa, sm)
    sum_b = corr(sm, sb)
    sum_a2 = corr(spec(fa * a), sm)
    sum_b2 = corr(sm, spec(fb * b))
    cross = corr(sa, sb)
    num = cross - sum_a * sum_b / n
    var_a = sum_a2 - sum_a**2 / n
    var_b = sum_b2 - sum_b**2 / n
    den = np.sqrt(np.maximum(var_a, 0) * np.maximum(var_b, 0))
    ok = den > 1e-9 * float(np.max(den))
    out: F64 = np.zeros(shape)
    np.divide(num, den, out=out, where=ok)
    out[n < MASKED_MIN_OVERLAP * float(m.sum())] = 0.0
    np.clip(out, -1.0, 1.0, out=out)
    return out


def coarse_shift(
    reference: npt.NDArray[np.floating],
    current: npt.NDArray[np.floating],
    *,
    prior_px: tuple[float, float] = (0.0, 0.0),
    static: BArr | None = None,
) -> CoarseShift:
    """Integer drift ``(dx, dy)`` in px from whole-image correlations.

    Two significances, each in standard deviations of its correlation
    surface: ``peak_z`` of the levelled-height peak (unrelated images give
    about ``sqrt(2 ln N)``, 4.1 for 200×200 px; consecutive HS-AFM frames
    7–12; the NanoScope pair 19) and ``gradient_z``, the correlation of the
    two x-gradient images at the same shift. Scan-line artefacts (streaks)
    correlate strongly in the levelled heights at spurious shifts (z 14–37
    on HS-AFM frames 22–31 of ``hsafm_sample_0.asd``) but not in the
    x-gradient (z about 0 there, 5–10 on good frames), so
    :attr:`CoarseShift.trusted` requires both. Wrap-around, lattice
    translations and static structure are handled as the module docstring
    describes.

    Parameters
    ----------
    reference, current : ndarray, shape (rows, cols)
        Height images of equal shape (finite; at least 2 columns).
    prior_px : (float, float)
        Expected drift: among shifts the images cannot tell apart (a
        lattice), the nearest to it is taken.
    static : ndarray of bool, optional
        Static pixels to leave out (:func:`static_pixels`); default: found
        here.

    Returns
    -------
    CoarseShift
    """
    a, b = _levelled(reference), _levelled(current)
    if static is None:
        static = static_pixels(reference, current)
    if static is not None:
        return _masked_shift(a, b, ~static, reference, current, prior_px)
    corr = _phase_correlation(a, b)
    spread = float(corr.std())
    n_rows, n_cols = corr.shape
    rows, cols = _local_peaks(corr, LATTICE_PEAK_RATIO * float(corr.max()))
    minimal = [
        (
            int(c) - n_cols if c > n_cols // 2 else int(c),
            int(r) - n_rows if r > n_rows // 2 else int(r),
        )
        for r, c in zip(rows, cols, strict=True)
    ]
    z_of = {s: float(corr[s[1] % n_rows, s[0] % n_cols]) / spread if spread > 0 else 0.0
            for s in minimal}  # fmt: skip
    near = sorted(minimal, key=lambda s: math.hypot(s[0] - prior_px[0], s[1] - prior_px[1]))
    pool = list(dict.fromkeys([minimal[0], *near[:LATTICE_CANDIDATES]]))
    unwrapped = {_unwrap(a, b, *s): z_of[s] for s in pool}
    chosen, lattice, ambiguous = _resolve(a, b, list(unwrapped), prior_px)
    g_ref, g_cur = _gradient(reference), _gradient(current)
    g_corr = _phase_correlation(g_ref, g_cur)
    g_z = _z(g_corr, chosen[1] % g_corr.shape[0], chosen[0] % g_corr.shape[1])
    return CoarseShift(
        float(chosen[0]), float(chosen[1]), unwrapped[chosen], g_z, lattice, ambiguous, "phase"
    )


def _resolve(
    a: F64, b: F64, shifts: list[tuple[int, int]], prior_px: tuple[float, float]
) -> tuple[tuple[int, int], tuple[tuple[float, float], ...], bool]:
    """Among candidate ``shifts`` (highest peak first), the one the content
    favours, or, among those it cannot tell apart, the nearest to the prior;
    with the other indistinguishable offsets and the ambiguity flag."""
    if len(shifts) > 1:
        # Only offsets at which the reference repeats itself (a local maximum of
        # its autocorrelation, within a pixel) are lattice translations; other
        # near-equal peaks (the flank of a broad peak) are not candidates.
        repeats = _self_similar(a)
        top = shifts[0]
        shifts = [top] + [
            s for s in shifts[1:] if _near(repeats, s[0] - top[0], s[1] - top[1], a.shape)
        ]
    if len(shifts) == 1:
        return shifts[0], (), False

    def dist(s: tuple[int, int]) -> float:
        return math.hypot(s[0] - prior_px[0], s[1] - prior_px[1])

    diff = {s: _difference(a, b, *s) for s in shifts}
    best = min(diff.values())
    same = [s for s in shifts if diff[s] <= LATTICE_MSE_RATIO * best + LATTICE_MSE_FLOOR]
    same.sort(key=dist)
    chosen = same[0]
    lattice = tuple(
        sorted(
            ((float(s[0] - chosen[0]), float(s[1] - chosen[1])) for s in same[1:]),
            key=lambda v: math.hypot(*v),
        )
    )
    ambiguous = len(same) > 1 and dist(same[1]) - dist(chosen) < 1.0
    return chosen, lattice, ambiguous


def _self_similar(a: F64) -> BArr:
    """Local maxima of the normalised autocorrelation of ``a`` (circular) of at
    least :data:`LATTICE_AC_MIN`, the origin excluded: the offsets at which the
    image repeats itself."""
    centred = a - a.mean()
    power = np.abs(np.fft.rfft2(centred)) ** 2
    ac: F64 = np.fft.irfft2(power, s=a.shape)
    if ac[0, 0] <= 0:
        return np.zeros(a.shape, dtype=bool)
    ac /= ac[0, 0]
    rows, cols = _local_peaks(ac, LATTICE_AC_MIN)
    mask = np.zeros(a.shape, dtype=bool)
    mask[rows, cols] = True
    mask[0, 0] = False
    return mask


def _near(mask: BArr, dx: int, dy: int, shape: tuple[int, ...]) -> bool:
    """Whether ``mask`` is set within one pixel of offset ``(dx, dy)`` (circular)."""
    rows, cols = shape
    return any(mask[(dy + i) % rows, (dx + j) % cols] for i in (-1, 0, 1) for j in (-1, 0, 1))


def _masked_shift(
    a: F64,
    b: F64,
    valid: BArr,
    reference: npt.NDArray[np.floating],
    current: npt.NDArray[np.floating],
    prior_px: tuple[float, float],
) -> CoarseShift:
    """Coarse shift with the static pixels left out (masked NCC); lattice
    translations among its peaks are resolved as for the phase correlation."""
    corr = _masked_ncc(a, b, valid)
    rows2, cols2 = corr.shape
    peak_rows, peak_cols = _local_peaks(corr, LATTICE_PEAK_RATIO * float(corr.max()))
    shifts = [
        (
            int(c) - cols2 if c >= cols2 // 2 else int(c),
            int(r) - rows2 if r >= rows2 // 2 else int(r),
        )
        for r, c in zip(peak_rows, peak_cols, strict=True)
    ]
    near = sorted(shifts, key=lambda s: math.hypot(s[0] - prior_px[0], s[1] - prior_px[1]))
    pool = list(dict.fromkeys([shifts[0], *near[:LATTICE_CANDIDATES]]))
    (dx, dy), lattice, ambiguous = _resolve(a, b, pool, prior_px)
    r, c = dy % rows2, dx % cols2
    spread = float(corr[corr != 0].std()) if np.any(corr != 0) else 0.0
    z = float(corr[r, c]) / spread if spread > 0 else 0.0
    g_ref, g_cur = _gradient(reference), _gradient(current)
    g_corr = _masked_ncc(g_ref, g_cur, valid[:, 1:] & valid[:, :-1])
    g_spread = float(g_corr[g_corr != 0].std()) if np.any(g_corr != 0) else 0.0
    g_z = float(g_corr[dy % rows2, dx % cols2]) / g_spread if g_spread > 0 else 0.0
    return CoarseShift(
        float(dx), float(dy), z, g_z, lattice, ambiguous, "masked", float(corr[r, c])
    )

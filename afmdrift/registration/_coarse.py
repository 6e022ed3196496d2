"""Whole-frame coarse alignment: the integer prior of the block search.

When no expected drift is known, one phase correlation of the two whole
height images gives the integer shift; the block windows are then moved by
it, so the block stage only has to resolve a small residual. That both
widens the measurable range beyond the block search radius and keeps the
window-induced bias of large in-window shifts away.

The shift is a peak of the phase correlation of the two images with their
per-line medians removed (line levelling, which takes out the line-to-line
offsets of AFM scans), their borders tapered (see the end of this
docstring). It is used only when two checks
agree (:attr:`CoarseShift.trusted`): the peak stands out of its correlation
surface, and the x-gradient images (eq. 2 of Yang et al. 2008, what the
block engine sees) also correlate at that shift. On the real NanoScope pair
(a lattice with a period of about 10 px) its highest peak is (0, 28), a
previous method (2×2-binned gradient images under a raised-cosine window)
gave (2, 18) and a Hann window on the heights 18 px as well: lattice
translations of each other, which the content of the two frames fits
equally well, so the pair is ambiguous (see *Lattices*).

Three things make a correlation peak lie, and each has its own step here:

* **Wrap-around.** A circular correlation cannot tell a shift ``d`` from
  ``d − N``: 350 px of a 450 px image and −100 px give the same peak. Each
  alternative is scored by the evidence of its overlap (at least
  :data:`MIN_OVERLAP_PX` per axis): the normalised cross-correlation of the
  levelled images there, times the square root of the overlap's share of
  the frame (the NCC of a thin strip is as high by chance as that of the
  whole frame is with half its content changed), and the best is kept.
* **Lattices.** On a periodic sample (graphite, a grating) the correlation
  has near-equal peaks at every lattice translation, and which is highest
  says little (on crops of a lattice the frame edges decide it). When the
  reference repeats itself (:func:`~afmdrift.registration._lattice.repeat_vectors`),
  the translations of the highest peak are compared by the content itself,
  with a paired test whose significance holds on noisy data
  (:func:`~afmdrift.registration._lattice.decide`): one that fits clearly
  better than every other is taken; among those it cannot tell apart, the
  one nearest the prior (the given or predicted drift) when it is clearly
  the nearest; otherwise the result is :attr:`CoarseShift.ambiguous` and
  names the tied translations (:attr:`CoarseShift.candidates_px`).
  :attr:`CoarseShift.period_px` keeps the lattice vectors, so the block
  search stays within half a period of the chosen translation.
* **Static structure.** A fixed mask, a border or an artefact burnt into both
  frames correlates perfectly at zero shift. Patches of pixels with exactly
  the same height in both frames are *static*; when they are present
  (but not everywhere: identical frames are simply not moved) and the phase
  correlation finds no trusted shift away from zero, the correlation is the
  masked normalised cross-correlation of Padfield (IEEE TIP 21(5), 2012)
  over the other pixels, zero-padded so that no shift wraps, and the peak
  is taken where at least :data:`MASKED_MIN_OVERLAP` of the pixels overlap.
  (Equal pixels are also the featureless ground of a sparse image, equal
  wherever it moved; where the phase correlation found a shift, they did not
  decide it.)

The frames' borders are tapered before the phase correlation (:func:`_taper`):
on smooth textures the wrap-around jumps and the corners, which both frames
share, would otherwise make the highest peak. A shift whose overlap lies in
the tapered border is found by correlating the whole frames when the tapered
correlation finds no trusted shift (and, in ``register``, when the blocks
fail around the one it found).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.registration._lattice import decide, local_peaks, repeat_vectors, subpixel_peak

__all__ = [
    "COARSE_MIN_GRADIENT_Z",
    "COARSE_MIN_Z",
    "NO_BOUND",
    "Bound",
    "CoarseShift",
    "coarse_shift",
    "format_shifts",
    "levelled",
    "overlap_slices",
    "static_pixels",
]

#: Smallest coarse correlation peak (in standard deviations of the surface) that is used.
COARSE_MIN_Z = 6.0
#: Smallest x-gradient correlation at the coarse shift (one location, so 3 sigma suffices).
COARSE_MIN_GRADIENT_Z = 3.0
#: Peaks at least this fraction of the highest, at a lattice translation of it, join
#: the candidates of the lattice decision.
LATTICE_PEAK_RATIO = 0.7
#: Correlation peaks considered besides the highest (those nearest the prior).
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


class Bound(NamedTuple):
    """What the user states about the drift between two frames and wants of a
    periodic sample (``RegistrationConfig.max_shift_px`` and ``lattice``).

    A stated bound is information: lattice translations beyond it are
    excluded (:func:`~afmdrift.registration._lattice.decide`), so a bound
    tighter than half a period decides the translation. ``equivalent``: the
    frames are to be registered, not the drift tracked, so among lattice
    translations the content cannot tell apart the one nearest the prior (or
    zero) is as good as any, and is taken."""

    max_shift_px: float | None = None
    equivalent: bool = False

    @classmethod
    def of(cls, config: RegistrationConfig) -> Bound:
        """The bound a configuration states."""
        return cls(config.max_shift_px, config.lattice == "equivalent")


#: No bound stated, lattice translations tracked.
NO_BOUND = Bound()


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
    apart (lattice translations of a periodic sample) and the prior set aside,
    shortest first."""
    ambiguous: bool = False
    """Lattice translations the images cannot tell apart, and neither a prior
    nor a stated bound decides between them, or none lies within the bound
    (:attr:`candidates_px`): no choice is defensible."""
    method: str = "phase"
    """``phase`` (phase correlation, borders tapered), ``phase, untapered`` (of
    the whole frames) or ``masked`` (static pixels left out)."""
    peak_ncc: float = math.nan
    """``masked``: the normalised cross-correlation at the shift (1: identical)."""
    period_px: tuple[tuple[float, float], ...] = ()
    """The reference's shortest lattice vectors (px, shortest first), empty when
    it does not repeat itself."""
    lattice_by: str = ""
    """How a lattice translation was chosen: ``content`` (it fits clearly
    better than its lattice neighbours), ``bound`` (tied in content, the only
    one within the stated bound), ``equivalent`` (tied, nearest the prior or
    zero, as asked), ``prior`` (tied in content, nearest the prior),
    ``ambiguous`` (none chosen), ``outside`` (none within the stated bound),
    ``rival`` (no lattice, but another high peak fits its overlap clearly
    better than the highest: :func:`_rival`), or empty (no lattice)."""
    candidates_px: tuple[tuple[float, float], ...] = ()
    """Tied lattice translations (sub-pixel shifts, px), nearest the prior (or
    zero) first (all of them, also those beyond a stated bound): every
    ``lattice_by`` but ``content``."""
    lattice_t: float = math.nan
    """The paired test's smallest statistic (a normal deviate) of the best
    translation against the others."""

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
    def tapered(self) -> bool:
        """The phase correlation of the frames with their borders tapered."""
        return self.method == "phase"

    @property
    def prior_px(self) -> tuple[float, float]:
        """``(dx, dy)`` when trusted, else ``(0, 0)``."""
        return (self.dx_px, self.dy_px) if self.trusted else (0.0, 0.0)

    def search_limit_px(self) -> float | None:
        """Largest block search half-width that cannot reach the next lattice
        translation (None without a lattice)."""
        vectors = self.period_px or self.lattice_px
        if not vectors:
            return None
        shortest = min(max(abs(a), abs(b)) for a, b in vectors)
        return max(1.0, math.ceil(shortest / 2) - 1)

    def describe(self) -> str:
        """One line for ``afmdrift measure`` and the result's ``prior``."""
        if self.method == "masked":
            text = f"masked correlation {self.peak_ncc:.2f} (static pixels left out)"
        else:
            text = f"{self.method} peak z={self.peak_z:.1f}, gradient z={self.gradient_z:.1f}"
        if self.lattice_by == "content":
            period = format_shifts(self.period_px[:1])
            text += (
                f"; lattice (period {period} px): the content decides "
                f"(z={self.lattice_t:.1f} against its lattice neighbours)"
            )
        elif self.lattice_by == "prior":
            text += (
                f"; lattice: also {format_shifts(self.lattice_px)} px fit as well, "
                "took the one nearest the prior"
            )
        elif self.lattice_by == "equivalent":
            text += (
                f"; lattice: also {format_shifts(self.lattice_px)} px fit as well, "
                "took the one nearest the prior (or zero): lattice-equivalent, as asked"
            )
        elif self.lattice_by == "bound":
            text += (
                f"; lattice: {format_shifts(self.candidates_px)} px fit alike, "
                "one alone within max_shift_px"
            )
        elif self.lattice_by == "rival":
            text += f"; two shifts fit: {format_shifts(self.candidates_px)} px"
        elif self.ambiguous:
            text += (
                f"; ambiguous: the lattice translations {format_shifts(self.candidates_px)} px "
                "fit as well"
            )
        return text


def format_shifts(shifts: tuple[tuple[float, float], ...], limit: int = 4) -> str:
    """``(+1.2, -3), (…)``: the first ``limit`` shifts, to 0.1 px."""
    text = ", ".join(f"({round(a, 1) + 0.0:+g}, {round(b, 1) + 0.0:+g})" for a, b in shifts[:limit])
    return text + (f", … ({len(shifts)} in all)" if len(shifts) > limit else "")


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


#: Share of each edge of a frame over which :func:`_taper` falls to zero.
TAPER = 1.0 / 16


def _taper(image: F64) -> F64:
    """``image`` times a Tukey window: one, falling to zero by a raised cosine
    over the outer :data:`TAPER` of each axis. Without it the jumps where the
    circular correlation wraps the frame (and worse, its corners, common to
    both frames) carry the whitened spectrum of a smooth texture: its highest
    peak sat within 2 px of zero for shifts of 4–20 px of 212² frames of a
    smooth background with a few sharp features, whichever the shift."""
    out = np.array(image, dtype=np.float64)
    windows = []
    for n in image.shape:
        k = int(n * TAPER)
        w = np.ones(n)
        if k >= 1:
            ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(k) + 0.5) / k))
            w[:k], w[n - k :] = ramp, ramp[::-1]
        windows.append(w)
    wy, wx = windows
    # Each line's (and column's) offset, weighted as the window weighs it,
    # comes off first: an offset times the window is the window's own shape,
    # the same in both frames, and would correlate at zero shift along the
    # other axis (unrelated frames reached z = 16 along dx = 0).
    out -= (out @ wx)[:, None] / wx.sum()
    out -= (wy @ out)[None, :] / wy.sum()
    out *= wy[:, None] * wx[None, :]
    return out


def _z_surface(corr: F64) -> F64:
    """``corr`` in standard deviations of its null: the larger of the
    surface's standard deviation and the robust spread (1.4826 × MAD) of
    the row and of the column each value lies in. A window multiplies both
    frames by the same separable profile, which correlates the spectrum
    along each axis and raises whole rows and columns of the correlation
    near the axes: unrelated 128²–512² frames reached z = 9.2–10.5 there
    (the plain correlation 4.9–5.2); per row and column they stay at
    4.7–5.3, as the plain correlation does either way."""
    spread = float(corr.std())
    if spread == 0:
        return np.zeros_like(corr)

    def mad(axis: int) -> F64:
        # per column through a contiguous transpose: numpy partitions
        # contiguous rows twice as fast as strided columns (same medians)
        lines = corr if axis == 1 else np.ascontiguousarray(corr.T)
        dev = np.abs(lines - np.median(lines, axis=1, keepdims=True))
        out: F64 = 1.4826 * np.median(dev, axis=1, keepdims=True)
        return out if axis == 1 else out.T

    out: F64 = corr / np.maximum(np.maximum(spread, mad(1)), mad(0))
    return out


def levelled(h: npt.NDArray[np.floating]) -> F64:
    """Heights with each scan line's median removed (line levelling)."""
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
    return _overlap_fit(a, b, dx, dy)[2]


def _share(shape: tuple[int, ...], dx: int, dy: int) -> float:
    """The share of a frame ``shape`` that overlaps at shift ``(dx, dy)``."""
    rows, cols = shape[0], shape[1]
    return (rows - abs(dy)) * (cols - abs(dx)) / (rows * cols)


def _overlap_fit(a: F64, b: F64, dx: int, dy: int) -> tuple[float, float, float]:
    """``(ncc, share, evidence)`` of the overlap at shift ``(dx, dy)``: the
    NCC once, its overlap's share of the frame, and the evidence of
    :func:`_overlap_score`."""
    ncc, share = _ncc(a, b, dx, dy), _share(a.shape, dx, dy)
    return ncc, share, ncc * math.sqrt(max(share, 0.0))


def overlap_evidence(
    reference: npt.NDArray[np.floating],
    current: npt.NDArray[np.floating],
    shifts: Sequence[tuple[float, float]],
) -> list[float]:
    """Evidence that ``current`` shows ``reference`` moved by each of
    ``shifts`` (px, rounded): the normalised cross-correlation of the
    levelled heights over their overlap times the square root of its share
    (:func:`_overlap_score`); ``-inf`` where they do not overlap by
    :data:`MIN_OVERLAP_PX` per axis. The frames are levelled once."""
    rows, cols = reference.shape
    a, b = levelled(reference), levelled(current)
    out = []
    for sx, sy in shifts:
        dx, dy = round(sx), round(sy)
        if cols - abs(dx) < MIN_OVERLAP_PX or rows - abs(dy) < MIN_OVERLAP_PX:
            out.append(-math.inf)
        else:
            out.append(_overlap_score(a, b, dx, dy))
    return out


def _unwrap(a: F64, b: F64, dx: int, dy: int, bound_px: float | None = None) -> tuple[int, int]:
    """The shift behind the circular peak at minimal-image shift ``(dx, dy)``:
    an alternative ``d ± N`` replaces it only when its overlap's evidence
    (:func:`_overlap_score`) is clearly larger (:data:`UNWRAP_MARGIN`); on a
    tie the larger overlap wins. An alternative whose overlap holds at least
    :data:`RIVAL_MIN_SHARE` of the frame and correlates clearly better
    (:data:`RIVAL_NCC_MARGIN`, and at least :data:`RIVAL_MIN_NCC`) wins
    too: a smooth background correlates over a large wrong overlap (450²
    crops of a retina photograph 350 px apart: NCC about 0.45 over 60 % of
    the frame, 1.0 over the true 17 %), which the evidence alone did not
    tell apart. Alternatives beyond a stated
    bound (``bound_px``, per axis) are not considered."""
    rows, cols = a.shape
    best_ncc, _, best_score = _overlap_fit(a, b, dx, dy)
    best = (dx, dy)
    alt_x = [dx] + ([dx - cols] if dx > 0 else [dx + cols] if dx < 0 else [])
    alt_y = [dy] + ([dy - rows] if dy > 0 else [dy + rows] if dy < 0 else [])
    if bound_px is not None:
        alt_x = [x for x in alt_x if x == dx or abs(x) <= bound_px + 1]
        alt_y = [y for y in alt_y if y == dy or abs(y) <= bound_px + 1]
    for ay in alt_y:
        for ax in alt_x:
            if (ax, ay) != (dx, dy):
                ncc, share, score = _overlap_fit(a, b, ax, ay)
                # a smooth background correlates over a large wrong overlap
                # (NCC 0.4-0.5 on the retina); the true, smaller one fits
                # nearly perfectly: clearly better fits win at a fair share
                fits = (
                    share >= RIVAL_MIN_SHARE
                    and ncc >= RIVAL_MIN_NCC
                    and ncc > best_ncc + RIVAL_NCC_MARGIN
                )
                if score > best_score + UNWRAP_MARGIN or fits:
                    best, best_score, best_ncc = (ax, ay), score, ncc
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
    prior_px: tuple[float, float] | None = None,
    static: BArr | None = None,
    taper: bool = True,
    ref_vectors: F64 | None = None,
    bound: Bound = NO_BOUND,
) -> CoarseShift:
    """Integer drift ``(dx, dy)`` in px from whole-image correlations.

    Two significances, each in standard deviations of its correlation
    surface (:func:`_z_surface`): ``peak_z`` of the levelled-height peak
    (unrelated images give about ``sqrt(2 ln N)``, 4.7–5.3 for 128²–512²
    px) and ``gradient_z``, the correlation of the
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
    prior_px : (float, float), optional
        Expected drift (given by a caller or predicted by a tracker): among
        lattice translations the content cannot tell apart, the one nearest
        it is taken when it is clearly the nearest. Without one such a tie
        is :attr:`CoarseShift.ambiguous`.
    static : ndarray of bool, optional
        Static pixels to leave out (:func:`static_pixels`); default: found
        here.
    taper : bool
        Taper the frames' borders before the phase correlation
        (:func:`_taper`); when that finds no trusted shift, the whole frames
        are correlated. False: the whole frames only.
    ref_vectors : ndarray, shape (k, 2), optional
        The reference's lattice vectors, when the caller has them:
        :func:`~afmdrift.registration._lattice.repeat_vectors` of
        ``levelled(reference)``; default: found here.
    bound : Bound
        What the user states about the drift (``max_shift_px``) and wants of
        a periodic sample (``lattice``); see :class:`Bound`.

    Returns
    -------
    CoarseShift
    """
    a, b = levelled(reference), levelled(current)
    # every way below decides lattice translations with them: found once
    vectors = repeat_vectors(a) if ref_vectors is None else ref_vectors
    if static is None:
        static = static_pixels(reference, current)
    phase = _phase_shift(a, b, reference, current, prior_px, vectors, bound, taper=taper)
    if taper and not (phase.trusted or phase.ambiguous):
        # A shift whose overlap lies in the tapered border (350 px of a 450 px
        # frame, both ways) is found without the taper.
        plain = _phase_shift(a, b, reference, current, prior_px, vectors, bound, taper=False)
        if plain.trusted or plain.ambiguous:
            phase = plain
    if static is None:
        return phase
    # Static structure pulls the phase correlation to zero shift. Where it
    # found a shift elsewhere, the equal pixels did not decide it: they are
    # featureless ground that is equal wherever it moved (a flat background
    # around one rectangle, the zeros of a frame of few photon counts), and
    # leaving them out would leave too little to correlate.
    if phase.trusted and max(abs(phase.dx_px), abs(phase.dy_px)) > 1:
        return phase
    return _masked_shift(a, b, ~static, reference, current, prior_px, vectors, bound)


def _phase_shift(
    a: F64,
    b: F64,
    reference: npt.NDArray[np.floating],
    current: npt.NDArray[np.floating],
    prior_px: tuple[float, float] | None,
    vectors: F64,
    bound: Bound,
    *,
    taper: bool,
) -> CoarseShift:
    """Coarse shift from the phase correlation of the levelled images ``a``
    and ``b`` (see :func:`coarse_shift`), their borders tapered
    (:func:`_taper`) or not; ``vectors``: ``a``'s lattice vectors."""
    corr = _phase_correlation(_taper(a) if taper else a, _taper(b) if taper else b)
    zs = _z_surface(corr)
    n_rows, n_cols = corr.shape
    rows, cols = local_peaks(zs, LATTICE_PEAK_RATIO * float(zs.max()))
    minimal = [
        (
            int(c) - n_cols if c > n_cols // 2 else int(c),
            int(r) - n_rows if r > n_rows // 2 else int(r),
        )
        for r, c in zip(rows, cols, strict=True)
    ]
    target = prior_px if prior_px is not None else (0.0, 0.0)
    near = sorted(minimal, key=lambda s: math.hypot(s[0] - target[0], s[1] - target[1]))
    pool = list(dict.fromkeys([minimal[0], *near[:LATTICE_CANDIDATES]]))
    top = _unwrap(a, b, *minimal[0], bound.max_shift_px)
    peaks = [_unwrap(a, b, *s, bound.max_shift_px) for s in pool[1:]]
    rival = None if len(vectors) else _rival(a, b, top, zs, bound.max_shift_px)
    lattice = _choose(a, b, corr, top, peaks, prior_px, vectors, bound) if rival is None else rival
    chosen = lattice.shift
    # The significance of the correlation is that of its highest peak; a
    # lattice translation of it is chosen by the content test, not by height.
    peak_z = float(zs[top[1] % n_rows, top[0] % n_cols])
    g_ref, g_cur = _gradient(reference), _gradient(current)
    if taper:
        g_ref, g_cur = _taper(g_ref), _taper(g_cur)
    g_zs = _z_surface(_phase_correlation(g_ref, g_cur))
    g_z = float(g_zs[chosen[1] % g_zs.shape[0], chosen[0] % g_zs.shape[1]])
    if lattice.by:
        # The x gradients support the correlation when they do at the highest
        # peak or at the lattice translation taken (the content took it).
        g_z = max(g_z, float(g_zs[top[1] % g_zs.shape[0], top[0] % g_zs.shape[1]]))
    return lattice.coarse(peak_z, g_z, "phase" if taper else "phase, untapered")


#: Other peaks of a sample without a lattice checked against the highest:
#: the highest few, of at least this fraction of its z (a match over a small
#: overlap makes a lower peak than one over the whole frame) ...
RIVAL_PEAKS = 4
RIVAL_PEAK_RATIO = 0.4
#: A rival's overlap must hold at least this share of the frame ...
RIVAL_MIN_SHARE = 0.10
#: ... and correlate better than the highest peak's by this much (NCC) ...
RIVAL_NCC_MARGIN = 0.2
#: ... and fit: the same content under noise correlates at SNR²/(1 + SNR²)
#: (0.8 at an SNR of 2), chance over a tenth of a 256² frame at about 0.05.
RIVAL_MIN_NCC = 0.5


def _rival(a: F64, b: F64, top: tuple[int, int], zs: F64, bound_px: float | None) -> _Choice | None:
    """A high peak that contests the highest (``top``), as an ambiguous
    choice naming both; None when none does.

    Evidence (:func:`_overlap_score`) weighs a match by the square root of
    its overlap, so that a thin strip that correlates by chance cannot take
    a frame; but a sample whose content repeats (a tiled texture, a
    self-similar surface) has a second true-looking match with a larger
    overlap and a worse fit: a 256² crop pair of a grass texture 12 % apart
    in area (NCC 0.99 over its overlap) had a peak at another shift with
    40 % of the frame overlapping at NCC 0.66, which the evidence preferred,
    and 11 blocks agreed on it. A rival whose overlap holds at least
    :data:`RIVAL_MIN_SHARE` of the frame and fits clearly better
    (:data:`RIVAL_NCC_MARGIN`, and at least :data:`RIVAL_MIN_NCC`) makes the
    pair ambiguous; only a highest peak that is itself significant
    (:data:`COARSE_MIN_Z`) is contested."""
    n_rows, n_cols = zs.shape
    peak_rows, peak_cols = local_peaks(zs, RIVAL_PEAK_RATIO * float(zs.max()))
    others = [
        (
            int(c) - n_cols if c > n_cols // 2 else int(c),
            int(r) - n_rows if r > n_rows // 2 else int(r),
        )
        for r, c in zip(peak_rows[1:], peak_cols[1:], strict=True)
    ]
    if zs[top[1] % n_rows, top[0] % n_cols] < COARSE_MIN_Z:
        return None  # no real correlation to contest (unrelated frames)
    top_ncc = _ncc(a, b, *top)
    for s in others[:RIVAL_PEAKS]:
        alt = _unwrap(a, b, *s, bound_px)
        share = _share(a.shape, *alt)
        if alt == top or share < RIVAL_MIN_SHARE:
            continue
        ncc = _ncc(a, b, *alt)
        if ncc >= RIVAL_MIN_NCC and ncc > top_ncc + RIVAL_NCC_MARGIN:
            tied = (float(top[0]), float(top[1])), (float(alt[0]), float(alt[1]))
            return _Choice(top, (), "rival", tied)
    return None


class _Choice(NamedTuple):
    """The shift :func:`_choose` took, with its lattice details."""

    shift: tuple[int, int]
    period: tuple[tuple[float, float], ...] = ()
    by: str = ""
    tied: tuple[tuple[float, float], ...] = ()
    t: float = math.nan

    def coarse(
        self, peak_z: float, gradient_z: float, method: str, ncc: float = math.nan
    ) -> CoarseShift:
        """The :class:`CoarseShift` of this choice, with the correlation's scores."""
        dx, dy = self.shift
        others = tuple(
            sorted(
                ((round(s[0] - dx, 1), round(s[1] - dy, 1)) for s in self.tied[1:]),
                key=lambda v: math.hypot(*v),
            )
        ) if self.by in ("prior", "equivalent") else ()  # fmt: skip
        refused = self.by in ("ambiguous", "outside", "rival")
        return CoarseShift(
            float(dx), float(dy), peak_z, gradient_z, others, refused, method,
            ncc, self.period, self.by, self.tied if self.by not in ("", "content") else (),
            self.t,
        )  # fmt: skip


#: Lattice vectors reported and used to narrow the block search.
PERIOD_VECTORS = 4


def _choose(
    a: F64,
    b: F64,
    corr: F64,
    top: tuple[int, int],
    peaks: list[tuple[int, int]],
    prior_px: tuple[float, float] | None,
    vectors: F64,
    bound: Bound,
) -> _Choice:
    """The shift of the highest peak ``top`` of the correlation surface
    ``corr``, or, when the reference repeats itself, the lattice translation
    of it that the content (or, among those it cannot tell apart, the prior)
    picks (:func:`afmdrift.registration._lattice.decide`); ``peaks`` are the
    other high peaks, those among them at a lattice translation of ``top``
    are candidates too; ``vectors``: the lattice vectors of ``a``
    (:func:`~afmdrift.registration._lattice.repeat_vectors`)."""
    if len(vectors) == 0:
        return _Choice(top)
    period = tuple((round(float(x), 2), round(float(y), 2)) for x, y in vectors[:PERIOD_VECTORS])
    start = subpixel_peak(corr, *top)
    translations = [
        subpixel_peak(corr, *s)
        for s in peaks
        if s != top and _is_translation(vectors, s[0] - top[0], s[1] - top[1])
    ]
    found = decide(
        a, b, start=start, peaks=translations, vectors=vectors, prior_px=prior_px,
        bound_px=bound.max_shift_px, equivalent=bound.equivalent,
    )  # fmt: skip
    tied = tuple((round(x, 1), round(y, 1)) for x, y in found.tied)
    if found.shift is None:
        near = found.tied[0] if found.tied else start
        return _Choice((round(near[0]), round(near[1])), period, found.by, tied, found.t)
    shift = (round(found.shift[0]), round(found.shift[1]))
    return _Choice(shift, period, found.by, tied, found.t)


def _is_translation(vectors: F64, dx: int, dy: int) -> bool:
    """Whether the offset ``(dx, dy)`` is within 1.5 px of a lattice vector."""
    return bool(np.min(np.hypot(vectors[:, 0] - dx, vectors[:, 1] - dy)) <= 1.5)


def _masked_shift(
    a: F64,
    b: F64,
    valid: BArr,
    reference: npt.NDArray[np.floating],
    current: npt.NDArray[np.floating],
    prior_px: tuple[float, float] | None,
    vectors: F64,
    bound: Bound,
) -> CoarseShift:
    """Coarse shift with the static pixels left out (masked NCC); lattice
    translations among its peaks are resolved as for the phase correlation
    (``vectors``: ``a``'s lattice vectors)."""
    corr = _masked_ncc(a, b, valid)
    rows2, cols2 = corr.shape
    peak_rows, peak_cols = local_peaks(corr, LATTICE_PEAK_RATIO * float(corr.max()))
    shifts = [
        (
            int(c) - cols2 if c >= cols2 // 2 else int(c),
            int(r) - rows2 if r >= rows2 // 2 else int(r),
        )
        for r, c in zip(peak_rows, peak_cols, strict=True)
    ]
    target = prior_px if prior_px is not None else (0.0, 0.0)
    near = sorted(shifts, key=lambda s: math.hypot(s[0] - target[0], s[1] - target[1]))
    pool = list(dict.fromkeys([shifts[0], *near[:LATTICE_CANDIDATES]]))
    choice = _choose(a, b, corr, pool[0], pool[1:], prior_px, vectors, bound)
    dx, dy = choice.shift
    r, c = dy % rows2, dx % cols2
    spread = float(corr[corr != 0].std()) if np.any(corr != 0) else 0.0
    z = float(corr[r, c]) / spread if spread > 0 else 0.0
    g_ref, g_cur = _gradient(reference), _gradient(current)
    g_corr = _masked_ncc(g_ref, g_cur, valid[:, 1:] & valid[:, :-1])
    g_spread = float(g_corr[g_corr != 0].std()) if np.any(g_corr != 0) else 0.0
    g_rows, g_cols = g_corr.shape  # the x gradient has a column fewer
    g_z = float(g_corr[dy % g_rows, dx % g_cols]) / g_spread if g_spread > 0 else 0.0
    return choice.coarse(z, g_z, "masked", float(corr[r, c]))

"""Frame-level drift: block combination, the one registration path
(:func:`register`) and :func:`measure_drift`."""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.registration._blocks import FrameStats, config_for_image
from afmdrift.registration._checks import (
    MIN_IMAGE_PX,
    allow_nearly_blank,
    check_frame,
    check_image,
    check_pixel_size,
    check_prior,
)
from afmdrift.registration._coarse import (
    Bound,
    CoarseShift,
    coarse_shift,
    format_shifts,
    levelled,
    overlap_evidence,
    overlap_slices,
)
from afmdrift.registration._distortion import (
    FieldFit,
    describe,
    distortion_limit_px,
    fit_field,
)
from afmdrift.registration._engine import BlockEngine, BlockMeasurement, ReferenceSpectra
from afmdrift.registration._errors import (
    NearlyBlankError,
    RegistrationError,
)
from afmdrift.registration._lattice import BOUND_SLACK_PX, repeat_vectors
from afmdrift.registration._outliers import needed_blocks, select_blocks
from afmdrift.registration._result import BlockField, DriftResult
from afmdrift.registration._trend import TREND_EXPLAINED, TREND_F

__all__ = [
    "REFINE_PX",
    "combine",
    "measure_blocks",
    "measure_drift",
    "warm_up",
]

#: A second block pass is made when the drift is farther than this from the prior (px).
REFINE_PX = 2.0

_CACHE_SIZE = 4
_cache_lock = threading.Lock()
_engines: OrderedDict[tuple[tuple[int, int], RegistrationConfig], BlockEngine] = OrderedDict()


def combine(
    meas: BlockMeasurement,
    *,
    engine: BlockEngine,
    pixel_size_nm: tuple[float, float],
    dtype: np.dtype[np.floating],
    textured: npt.NDArray[np.bool_] | None = None,
) -> DriftResult:
    """Reject outlier blocks and reduce the block vectors to one drift.

    ``textured``: the blocks whose reference content stands out of the noise
    (:func:`textured_blocks`); when given, only they count towards the
    blocks a valid result needs (``min_valid_fraction``)."""
    cfg = engine.config
    vec = meas.vectors_px
    measured = meas.measured
    # The valid blocks, their mean and spread: the one selection path.
    sel = select_blocks(
        vec, measured, meas.placed, meas.in_overlap, row_px=meas.centres_px[:, 1], config=cfg,
        textured=textured,
    )  # fmt: skip
    valid, n_valid, available = sel.valid, sel.n_valid, sel.available
    (mean_x, mean_y), (spread_x, spread_y) = sel.mean_px, sel.spread_px
    total = int(vec.shape[0])
    field = BlockField(
        centres_px=meas.centres_px.astype(dtype),
        vectors_px=vec.astype(dtype),
        confidence=meas.confidence.astype(dtype),
        mse=meas.mse.astype(dtype),
        measured=measured.copy(),
        valid=valid,
        weight_centres_px=meas.weight_centres_px.astype(dtype),
    )
    reason = None
    need = needed_blocks(cfg, available)
    if n_valid < need:
        counted = "in the overlap" if textured is None else "with texture in the overlap"
        reason = (
            f"only {n_valid} of {total} blocks valid (need {need}: {available} {counted}, "
            f"{int(measured.sum())} with a usable peak)"
        )
    elif not max(spread_x, spread_y) <= cfg.max_block_spread_px:
        reason = (
            f"the {n_valid} valid blocks disagree: residual spread about their trend over "
            f"the rows ({spread_x:.2f}, "
            f"{spread_y:.2f}) px exceeds max_block_spread_px = {cfg.max_block_spread_px}"
        )
    if total > SMALL_FRAME_BLOCKS and cfg.outlier_rule == "mad":
        bent = _non_rigid(meas, engine, need, textured, start=None if reason is not None else valid)
        if isinstance(bent, str):
            reason = bent
        elif bent is not None:
            return _field_result(bent, field, pixel_size_nm, total)
    if reason is not None:
        return invalid_result(field, reason, valid_blocks=n_valid)
    # Blocks whose inner areas overlap are not independent: count each only
    # by its unshared fraction (never fewer than two blocks).
    root_n = math.sqrt(max(2.0, n_valid * engine.layout.overlap_factor()))
    sigma = (spread_x / root_n, spread_y / root_n)
    return _valid_result((mean_x, mean_y), sigma, pixel_size_nm, n_valid, total, field)


def _valid_result(
    mean_px: tuple[float, float],
    sigma_px: tuple[float, float],
    pixel_size_nm: tuple[float, float],
    n_valid: int,
    total: int,
    field: BlockField,
    distortion_px: tuple[float, float] | None = None,
) -> DriftResult:
    """A valid frame result from its mean and σ (px)."""
    px, py = pixel_size_nm
    (mx, my), (sx, sy) = mean_px, sigma_px
    sx_nm, sy_nm = sx * px, sy * py
    return DriftResult(
        dx_px=mx,
        dy_px=my,
        dx_nm=mx * px,
        dy_nm=my * py,
        sigma_x_nm=sx_nm,
        sigma_y_nm=sy_nm,
        sigma_nm=math.sqrt(0.5 * (sx_nm**2 + sy_nm**2)),
        valid=True,
        valid_blocks=n_valid,
        total_blocks=total,
        reason=None,
        field=field,
        distortion_px=distortion_px,
    )


def _non_rigid(
    meas: BlockMeasurement,
    engine: BlockEngine,
    need: int,
    textured: npt.NDArray[np.bool_] | None,
    *,
    start: npt.NDArray[np.bool_] | None,
) -> FieldFit | str | None:
    """A non-rigid frame (:mod:`._distortion`): the smooth field over the
    frame (:func:`fit_field`) when it explains the blocks (enough kept, their
    residual spread about it within ``max_block_spread_px``) and either the
    one shift or trend over the rows was refused (``start`` None) or, fitted
    first on the blocks they kept (``start``), the field's dependence on the
    column is significant; a refusal's reason when so,
    but the distortion is beyond :func:`distortion_limit_px`; None
    otherwise (a rigid frame, or blocks that disagree: changed content,
    false peaks)."""
    cfg = engine.config
    placed_ok = int(np.count_nonzero(meas.measured & meas.placed)) >= cfg.min_valid_blocks
    usable = meas.measured & (meas.placed if placed_ok else meas.in_overlap)
    if textured is not None:
        usable = usable & textured
    rows, cols = engine.image_shape
    fit = fit_field(
        meas.vectors_px, meas.weight_centres_px, usable, frame_shape=(rows, cols),
        independent=engine.layout.overlap_factor(), f_min=TREND_F,
        explained_min=TREND_EXPLAINED, start=start, force=start is None,
    )  # fmt: skip
    refused = start is None
    if fit is None or int(fit.valid.sum()) < need or not (refused or fit.significant):
        return None
    if not max(fit.spread_px) <= cfg.max_block_spread_px:
        return None
    limit = distortion_limit_px(cfg.block_size)
    if max(fit.distortion_px) > limit:
        return (
            f"{describe(fit)}, but its parts moved apart by more than {limit:g} px RMS "
            f"(an eighth of the {cfg.block_size} px block): a block's own window then "
            "holds content displaced by more than a pixel, and no single shift places "
            "the frame"
        )
    return fit


def _field_result(
    fit: FieldFit, field: BlockField, pixel_size_nm: tuple[float, float], total: int
) -> DriftResult:
    """The drift of a non-rigid frame (:class:`FieldFit`), its valid blocks
    those the field kept."""
    return _valid_result(
        fit.mean_px, fit.sigma_px, pixel_size_nm, int(fit.valid.sum()), total,
        replace(field, valid=fit.valid), fit.distortion_px,
    )  # fmt: skip


def invalid_result(field: BlockField, reason: str, *, valid_blocks: int = 0) -> DriftResult:
    """A refused measurement: NaN numbers, ``valid`` False, the ``reason``."""
    nan = math.nan
    return DriftResult(
        dx_px=nan,
        dy_px=nan,
        dx_nm=nan,
        dy_nm=nan,
        sigma_x_nm=nan,
        sigma_y_nm=nan,
        sigma_nm=nan,
        valid=False,
        valid_blocks=valid_blocks,
        total_blocks=int(field.vectors_px.shape[0]),
        reason=reason,
        field=field,
    )


def _no_field(engine: BlockEngine, dtype: np.dtype[np.floating]) -> BlockField:
    """The block field of a frame pair whose blocks were not measured."""
    n = engine.layout.n_blocks
    return BlockField(
        centres_px=engine.centres_px.astype(dtype),
        vectors_px=np.full((n, 2), np.nan, dtype=dtype),
        confidence=np.zeros(n, dtype=dtype),
        mse=np.full(n, np.nan, dtype=dtype),
        measured=np.zeros(n, dtype=bool),
        valid=np.zeros(n, dtype=bool),
        weight_centres_px=engine.centres_px.astype(dtype),
    )


@dataclass(frozen=True, eq=False)
class Registration:
    """What :func:`register` found: the result, the window corners used in the
    current frame (``top``, ``left``: its spectra can become the next
    reference) and the coarse alignment, when one was made (and its
    untapered alternative, when that was tried in vain)."""

    result: DriftResult
    top: npt.NDArray[np.intp]
    left: npt.NDArray[np.intp]
    coarse: CoarseShift | None
    #: The whole-frame coarse alignment tried after the tapered one failed.
    alternative: CoarseShift | None = None


@dataclass(frozen=True, eq=False)
class _Pair:
    """What :func:`register` measures: the engine, the reference (its
    spectra, and its heights for the coarse alignment), the current frame's
    gradient buffer and heights, and the pixel size."""

    engine: BlockEngine
    ref: ReferenceSpectra
    grad: npt.NDArray[np.float32]
    heights: npt.NDArray[np.floating]
    ref_heights: npt.NDArray[np.floating] | None
    pixel_size_nm: tuple[float, float]

    def coarse(self, prior_px: tuple[float, float] | None, *, taper: bool = True) -> CoarseShift:
        """The coarse alignment of the frame on the reference (its lattice
        vectors found once, :func:`_vectors`)."""
        assert self.ref_heights is not None
        return coarse_shift(
            self.ref_heights, self.heights, prior_px=prior_px, taper=taper,
            ref_vectors=_vectors(self.ref, self.ref_heights),
            bound=Bound.of(self.engine.config),
        )  # fmt: skip

    def combine(
        self, meas: BlockMeasurement, textured: npt.NDArray[np.bool_] | None
    ) -> DriftResult:
        """:func:`combine` for this pair."""
        return combine(
            meas, engine=self.engine, pixel_size_nm=self.pixel_size_nm,
            dtype=result_dtype(self.heights), textured=textured,
        )  # fmt: skip


@dataclass(eq=False)
class _Attempt:
    """Where :func:`register` stands: the prior the blocks were (or are to be)
    searched around, the search half-width, how the prior came about, the
    lattice translations the result stands among, the coarse alignments
    made, and, once measured, the result and window corners."""

    prior: tuple[float, float] = (0.0, 0.0)
    search: float | None = None
    how: str = "none"
    coarse: CoarseShift | None = None
    alternative: CoarseShift | None = None
    #: Whether the frame's gradient image was made and checked already.
    checked: bool = False
    #: The pair refused before any block pass (ambiguous lattice translations).
    refused: Registration | None = None
    result: DriftResult | None = None
    top: npt.NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    left: npt.NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    lattice: tuple[tuple[float, float], ...] = ()
    #: The expected drift given or predicted, before a coarse alignment moved the search.
    expected: tuple[float, float] | None = None

    def registration(self) -> Registration:
        assert self.result is not None
        result = replace(
            self.result,
            prior_px=self.prior,
            prior=self.how,
            lattice_px=self.lattice,
            expected_px=self.expected,
        )
        if result.valid:
            result = _decided(result, self.coarse if self.lattice or _tied(self.coarse) else None)
        return Registration(result, self.top, self.left, self.coarse, self.alternative)


def _tied(coarse: CoarseShift | None) -> bool:
    """Whether ``coarse`` took a lattice translation among tied ones."""
    return coarse is not None and coarse.lattice_by in ("prior", "equivalent", "bound")


def _decided(result: DriftResult, coarse: CoarseShift | None) -> DriftResult:
    """``result`` with what decided it (:attr:`DriftResult.decided_by`) when
    the coarse alignment it was measured around took a lattice translation
    among tied ones: the prior (the one nearest it), ``bound`` (the only one
    within ``max_shift_px``) or ``equivalent`` (nearest the prior or zero, as
    asked); else the content. ``alternatives_px``: the other tied shifts
    (within the bound, for ``bound`` none, those beyond it)."""
    if coarse is None or not _tied(coarse):
        return replace(result, decided_by="content")
    d = (result.dx_px, result.dy_px)
    others = tuple(c for c in coarse.candidates_px if math.hypot(c[0] - d[0], c[1] - d[1]) > 0.5)
    if not others:
        return replace(result, decided_by="content")
    ambiguity = min(math.hypot(c[0] - d[0], c[1] - d[1]) for c in others)
    return replace(
        result, decided_by=coarse.lattice_by, alternatives_px=others, ambiguity_px=ambiguity
    )


def register(
    engine: BlockEngine,
    ref: ReferenceSpectra,
    grad: npt.NDArray[np.float32],
    heights: npt.NDArray[np.floating],
    *,
    ref_heights: npt.NDArray[np.floating] | None,
    expected_px: tuple[float, float] | None,
    source: str,
    pixel_size_nm: tuple[float, float],
    check: Callable[[FrameStats], None] | None = None,
    miss_px: float = 0.0,
) -> Registration:
    """The one registration path of :func:`measure_drift`, :class:`DriftTracker`
    and ``afmdrift measure``: prior → block pass → refine → combine, with the
    coarse alignment where nothing is expected or the first try fails.

    1. **Prior** (:func:`_choose_prior`). ``expected_px`` (``source``:
       ``given`` by a caller, ``predicted`` by the tracker) centres the block
       search. Without it, the coarse alignment :func:`coarse_shift`
       (``config.coarse``) does, within ±``coarse_search_px`` (less on a
       lattice: never as far as the next lattice translation); an untrusted
       one leaves zero and the full search. When the reference repeats
       itself (a lattice, :func:`reference_repeats`), the coarse alignment
       decides the lattice translation with ``expected_px`` too (by content,
       else the one nearest it). Lattice translations that neither the
       content nor the expected drift decide between are refused as
       ambiguous, naming them.
    2. **Blocks**, refined once around their median (:func:`measure_blocks`),
       and combined (:func:`combine`).
    3. **Retry** (:func:`_retry`). A result that came out invalid is measured
       once more around the trusted coarse alignment (the lattice translation
       nearest the expectation), when that differs from the first prior.

    ``grad`` holds the current frame's gradient image, or, with ``check``,
    is filled from ``heights`` during the first block pass (see
    :meth:`BlockEngine.measure`) and checked by ``check``.
    """
    pair = _Pair(engine, ref, grad, heights, ref_heights, pixel_size_nm)
    at = _choose_prior(pair, expected_px=expected_px, source=source, check=check)
    if at.refused is not None:
        return at.refused
    fresh = check is not None and not at.checked
    meas, at.top, at.left = measure_blocks(
        engine,
        ref,
        grad,
        prior_px=at.prior,
        search_px=at.search,
        heights=heights if fresh else None,
        check=check if fresh else None,
    )
    # Featureless blocks (flat substrate between particles) do not count
    # towards the blocks a valid result needs. They still vote: a block whose
    # texture is below the noise per pixel still locks over its thousands of
    # pixels, and leaving whole block rows out moves the scan time the
    # frame's mean stands for (a down frame's rows run the other way), which
    # put up and down frames ±0.2 nm apart on quiet-lab-24h; the random peaks
    # of a bare substrate fall to the outlier rule.
    textured = textured_blocks(engine, ref)
    at.result = pair.combine(meas, textured)
    if at.coarse is not None and at.search is not None:
        at.lattice = at.coarse.lattice_px
    if not at.result.valid and ref_heights is not None:
        _retry(at, pair, expected_px=expected_px, textured=textured)
    elif (
        expected_px is not None and at.search is None and _suspect(at.result, expected_px, miss_px)
    ):
        _check_by_coarse(at, pair, expected_px=expected_px, textured=textured)
    if at.result is not None:
        at.result = check_bound(at.result, engine.config.max_shift_px, pixel_size_nm)
    return at.registration()


def check_bound(
    r: DriftResult, bound_px: float | None, pixel_size_nm: tuple[float, float]
) -> DriftResult:
    """``r``, or, when it is valid and beyond the stated bound
    (``max_shift_px``, per axis, by more than three σ), a refusal: the frames
    moved farther than the user says they can, or the content changed, and
    either way the number is not the one asked for."""
    if bound_px is None or not r.valid:
        return r
    sx, sy = r.sigma_x_nm / pixel_size_nm[0], r.sigma_y_nm / pixel_size_nm[1]
    over_x = abs(r.dx_px) - bound_px - max(BOUND_SLACK_PX, 3 * sx)
    over_y = abs(r.dy_px) - bound_px - max(BOUND_SLACK_PX, 3 * sy)
    if over_x <= 0 and over_y <= 0:
        return r
    return invalid_result(
        r.field,
        f"beyond the bound: the blocks give ({r.dx_px:+.1f}, {r.dy_px:+.1f}) px, farther than "
        f"max_shift_px = {bound_px:g} px; the frames moved farther than stated, or the "
        "content changed",
        valid_blocks=r.valid_blocks,
    )


#: A valid result around an expected position is checked against the
#: whole-frame alignment when it lands this far from the expectation (px,
#: either axis) ...
CHECK_OFF_PX = 2.0
#: ... or rests on fewer than this share of its blocks. Blocks whose windows
#: overlap (small frames: 16 windows of two thirds of a 128² frame) see much
#: the same content and can agree on one false peak when the content jumped
#: farther than expected (an unlogged offset move): 15 of 16 blocks put a
#: 128² frame (+5, -6) px from the prior where it had moved (-28, +8) px.
CHECK_VALID_SHARE = 0.5
#: Evidence margin (:func:`overlap_evidence`) by which one of two valid shifts
#: must beat the other; closer than this, the pair is refused.
EVIDENCE_MARGIN = 0.1


#: Frames of at most this many blocks (a 128² frame has 16, a 64² frame 12)
#: have windows so alike that their votes count for little: a result there is
#: checked from :data:`SMALL_CHECK_OFF_PX` off, or under
#: :data:`SMALL_CHECK_VALID_SHARE` of its blocks (12 windows of a 64² frame put
#: (+1.2, -1.4) px, 9 of them agreeing, where the content had jumped 14 px;
#: 7 of 12 put another 64² frame 0.1 px from the prediction, 250 nm off). On
#: a 128² track about half the frames are checked, at a few ms each.
SMALL_FRAME_BLOCKS = 16
SMALL_CHECK_OFF_PX = 1.0
SMALL_CHECK_VALID_SHARE = 0.8


#: ... and, on frames of more blocks, where the expectation is a prediction,
#: from this many times the robust spread of its recent misses: a drift that
#: is hard to predict (a fast curved path misses a constant-velocity
#: prediction by 2-9 px every frame) would otherwise send every 512² frame
#: through the coarse alignment.
CHECK_MISS_K = 3.0


def _suspect(result: DriftResult, expected_px: tuple[float, float], miss_px: float) -> bool:
    """Whether a valid result around ``expected_px`` is checked (see
    :data:`CHECK_OFF_PX`; ``miss_px``: the robust spread of the recent
    prediction misses, 0 for a given prior); a coarse alignment costs tens
    of block passes, so a result where it was expected, on most of its
    blocks, is not."""
    off = max(abs(result.dx_px - expected_px[0]), abs(result.dy_px - expected_px[1]))
    small = result.total_blocks <= SMALL_FRAME_BLOCKS
    # small frames are checked whatever the misses: their blocks' agreement
    # says least, and their coarse alignment costs least
    limit = SMALL_CHECK_OFF_PX if small else max(CHECK_OFF_PX, CHECK_MISS_K * miss_px)
    share = SMALL_CHECK_VALID_SHARE if small else CHECK_VALID_SHARE
    return off > limit or result.valid_blocks < share * result.total_blocks


def _check_by_coarse(
    at: _Attempt,
    pair: _Pair,
    *,
    expected_px: tuple[float, float],
    textured: npt.NDArray[np.bool_],
) -> None:
    """Step 4 of :func:`register`, for a suspect valid result (:func:`_suspect`):
    the whole-frame coarse alignment, when trusted and farther from the result
    than the block search around it, is measured too; of two valid results
    the one whose overlap shows the same sample clearly better
    (:func:`overlap_evidence`) is taken, and a pair whose two shifts fit
    alike is refused, naming both. A coarse alignment whose blocks do not
    agree replaces nothing, but refuses a result its overlap clearly beats."""
    if not pair.engine.config.coarse or pair.ref_heights is None:
        return
    coarse = pair.coarse(expected_px)
    if not coarse.trusted:
        return
    first = at.result
    assert first is not None
    cx, cy = coarse.prior_px
    reach = _coarse_search(pair.engine.config, coarse) + 1.0
    if abs(first.dx_px - cx) <= reach and abs(first.dy_px - cy) <= reach:
        return
    kept = (at.result, at.top, at.left, at.prior, at.how, at.lattice)
    at.coarse = coarse
    e_first, e_coarse = overlap_evidence(
        pair.ref_heights, pair.heights, [(first.dx_px, first.dy_px), (cx, cy)]
    )
    where = (
        f"the blocks around the expected position give ({first.dx_px:+.1f}, "
        f"{first.dy_px:+.1f}) px, the whole-frame alignment ({cx:+.0f}, {cy:+.0f}) px"
    )
    measured = _measure_around(at, pair, coarse, textured)
    if measured and e_coarse > e_first + EVIDENCE_MARGIN:
        at.how = f"{at.how}; {where}: the overlap decides"
        return
    at.result, at.top, at.left, at.prior, at.how, at.lattice = kept
    # both measured: the first stands only where its overlap is clearly
    # better; the coarse alignment's blocks disagreeing: where the coarse
    # overlap is not clearly better
    if (
        (e_first > e_coarse + EVIDENCE_MARGIN)
        if measured
        else not (e_coarse > e_first + EVIDENCE_MARGIN)
    ):
        return
    at.result = invalid_result(
        first.field,
        f"two shifts fit: {where} (overlap evidence {e_first:.2f} and {e_coarse:.2f}); "
        "the frame content jumped farther than expected or changed",
        valid_blocks=first.valid_blocks,
    )


def _choose_prior(
    pair: _Pair,
    *,
    expected_px: tuple[float, float] | None,
    source: str,
    check: Callable[[FrameStats], None] | None,
) -> _Attempt:
    """Step 1 of :func:`register`: the prior and search of the block pass,
    from ``expected_px`` (decided among lattice translations on a periodic
    sample) or the coarse alignment. The coarse alignment needs the frame
    checked first: with ``check``, its gradient image is made into the
    pair's gradient buffer and checked then. A pair whose lattice
    translations tie with nothing to decide comes back ``refused``."""
    engine, ref = pair.engine, pair.ref
    cfg = engine.config
    at = _Attempt(expected=expected_px)
    if expected_px is not None:
        at.prior, at.how = expected_px, source
    if not cfg.coarse or pair.ref_heights is None:
        return at
    if expected_px is not None and not reference_repeats(ref, pair.ref_heights):
        return at
    # Nothing expected, or a periodic sample: blocks searching ±max_shift_px
    # around the expected drift lock onto whichever lattice translation their
    # own peaks favour (a given prior 3 px from the truth once gave a valid
    # result a period off). The lattice decision of the coarse alignment
    # picks the translation (by content, else the one nearest the
    # expectation), and the blocks search around it only.
    if check is not None:
        check(engine.prepare(pair.heights, out=pair.grad)[1])
        at.checked = True
    at.coarse = coarse = pair.coarse(expected_px)
    if coarse.ambiguous:
        result = invalid_result(
            _no_field(engine, result_dtype(pair.heights)), ambiguous_reason(coarse)
        )
        result = replace(
            result,
            prior_px=expected_px,
            prior=coarse.describe() if expected_px is None else f"{source}; {coarse.describe()}",
            lattice_px=coarse.candidates_px,
            expected_px=expected_px,
        )
        empty = np.zeros(0, dtype=np.intp)
        at.refused = Registration(result, empty, empty, coarse)
    elif expected_px is not None and coarse.lattice_by and coarse.trusted:
        at.prior, at.search = coarse.prior_px, _coarse_search(cfg, coarse)
        at.how = f"{source}, lattice translation by the coarse alignment ({coarse.describe()})"
    elif expected_px is not None:
        # No lattice decision to go by: the blocks search only up to half a
        # period around the expected drift.
        at.search = _lattice_search(cfg, ref)
        at.how = f"{source}; search within half the reference's period"
    elif coarse.trusted:
        at.prior, at.search = coarse.prior_px, _coarse_search(cfg, coarse)
        at.how = f"coarse ({coarse.describe()})"
    else:
        at.how = f"coarse not used ({coarse.describe()})"
    return at


def _retry(
    at: _Attempt,
    pair: _Pair,
    *,
    expected_px: tuple[float, float] | None,
    textured: npt.NDArray[np.bool_],
) -> None:
    """Step 3 of :func:`register`, for a result that came out invalid:
    measure once more around the trusted coarse alignment (made now if the
    prior did not come from it), or, when the blocks searched around a
    tapered coarse alignment, around the alignment of the untapered frames;
    ``at`` takes the second result if it is valid."""
    coarse = at.coarse
    if pair.engine.config.coarse and at.search is None:
        if coarse is None or expected_px is not None:
            coarse = at.coarse = pair.coarse(expected_px)
        if coarse.trusted:
            _measure_around(at, pair, coarse, None)
        return
    if coarse is None or not (coarse.trusted and coarse.tapered):
        return
    # The taper keeps the frame edges out of the correlation, but also an
    # overlap that lies in the tapered border (shifts of most of the frame
    # both ways); the correlation of the whole frames is the other candidate,
    # and the blocks (or the overlap, measure_drift) decide.
    plain = pair.coarse(expected_px, taper=False)
    if plain.trusted and plain.prior_px != coarse.prior_px:
        at.alternative = plain
        if _measure_around(at, pair, plain, textured):
            at.coarse, at.alternative = plain, None


def _measure_around(
    at: _Attempt, pair: _Pair, coarse: CoarseShift, textured: npt.NDArray[np.bool_] | None
) -> bool:
    """The blocks measured around the trusted ``coarse`` alignment and
    combined (``textured``: see :func:`combine`); taken into ``at`` and True
    when the result is valid."""
    engine = pair.engine
    retry, top, left = measure_blocks(
        engine, pair.ref, pair.grad, prior_px=coarse.prior_px,
        search_px=_coarse_search(engine.config, coarse),
    )  # fmt: skip
    again = pair.combine(retry, textured)
    if not again.valid:
        return False
    at.result, at.top, at.left, at.prior = again, top, left, coarse.prior_px
    at.how, at.lattice = f"coarse retry ({coarse.describe()})", coarse.lattice_px
    return True


#: A block has texture when its reference content's variance is at least this
#: multiple of the pre-filtered image's noise variance.
TEXTURE_NOISE_RATIO = 2.0
#: ... and blocks are told apart only when some block's variance reaches this
#: multiple (a texture as fine as the noise cannot be told from it in one frame).
TEXTURE_CONTRAST = 8.0


def textured_blocks(engine: BlockEngine, ref: ReferenceSpectra) -> npt.NDArray[np.bool_]:
    """Blocks whose reference window (its content under the raised cosine,
    what the block correlates) stands out of the noise (computed once per
    reference and kept with it).

    The white-noise level of the pre-filtered reference is estimated robustly
    from its differences along x (σ² = (1.4826 · MAD)² / 6 of the second
    difference of the heights, which the x gradient's first difference is;
    ×2 for the x gradient's own noise), and a block has texture when its
    window-weighted variance is at least :data:`TEXTURE_NOISE_RATIO` times that, provided
    some block reaches :data:`TEXTURE_CONTRAST` times it (otherwise every
    block counts). Flat substrate between particles has none; noise-free
    frames count every block that is not exactly flat."""
    cached = ref.derived.get("textured")
    if cached is not None:
        return cached
    g = ref.grad.astype(np.float64)
    if engine.prefilter in ("x", "both"):
        d = np.diff(g[::2], axis=1)
        noise = 2.0 * (1.4826 * float(np.median(np.abs(d - np.median(d))))) ** 2 / 6.0
    else:
        d = g[::2, 2:] - 2.0 * g[::2, 1:-1] + g[::2, :-2]
        noise = (1.4826 * float(np.median(np.abs(d - np.median(d))))) ** 2 / 6.0
    ey, ex = engine.layout.ext
    w = engine.window.astype(np.float64)
    w /= w.sum()

    def weighted_var(block: npt.NDArray[np.float64]) -> float:
        mean = float(np.sum(w * block))
        return float(np.sum(w * (block - mean) ** 2))

    # what each window correlates: its content under the raised cosine
    var = np.array(
        [
            weighted_var(g[t : t + ey, lft : lft + ex])
            for t, lft in zip(ref.top, ref.left, strict=True)
        ]
    )
    if noise > 0:
        out = var > TEXTURE_NOISE_RATIO * noise
        if not np.any(var > TEXTURE_CONTRAST * noise):
            # No block stands clearly out: a texture as fine as the noise (or
            # noise alone) everywhere. Nothing marks any block as substrate.
            out[:] = True
    else:
        out = var > 0
    ref.derived["textured"] = out
    return out


def reference_repeats(ref: ReferenceSpectra, ref_heights: npt.NDArray[np.floating]) -> bool:
    """Whether the reference repeats itself (a lattice: :func:`repeat_vectors`
    of its levelled heights finds a vector), computed once per reference and
    kept with it, with its vectors (``derived["repeats"]``)."""
    cached = ref.derived.get("repeats")
    if cached is None:
        cached = _vectors(ref, ref_heights)
        ref.derived["repeats"] = cached
    return len(cached) > 0


def _vectors(
    ref: ReferenceSpectra, ref_heights: npt.NDArray[np.floating]
) -> npt.NDArray[np.float64]:
    """:func:`repeat_vectors` of the levelled ``ref_heights``, kept with
    ``ref`` for these very heights (``derived["vectors"]``, of
    ``derived["vectors_of"]``): the coarse alignments of the frames measured
    against it and :func:`reference_repeats` need them."""
    if ref.derived.get("vectors_of") is ref_heights:
        return ref.derived["vectors"]
    vectors = repeat_vectors(levelled(np.asarray(ref_heights)))
    ref.derived["vectors_of"] = ref_heights
    ref.derived["vectors"] = vectors
    return vectors


def _lattice_search(cfg: RegistrationConfig, ref: ReferenceSpectra) -> float:
    """Block search half-width that cannot reach the next lattice translation
    of the reference (:func:`reference_repeats` found its vectors)."""
    vectors = ref.derived["repeats"]
    shortest = float(np.min(np.max(np.abs(vectors), axis=1)))
    return min(cfg.coarse_search_px, max(1.0, math.ceil(shortest / 2) - 1))


def _coarse_search(cfg: RegistrationConfig, coarse: CoarseShift) -> float:
    """Block search half-width around a trusted coarse prior."""
    limit = coarse.search_limit_px()
    return cfg.coarse_search_px if limit is None else min(cfg.coarse_search_px, limit)


def ambiguous_reason(coarse: CoarseShift) -> str:
    """Why a pair whose lattice translations tie is refused, naming them."""
    if coarse.lattice_by == "rival":
        return (
            f"ambiguous: two shifts fit, {format_shifts(coarse.candidates_px)} px: the first "
            "by the highest correlation peak over a larger overlap, the second clearly better "
            "over its own; the sample's content repeats, or it changed; give the expected "
            "drift (--prior-px DX DY, prior_px) or the largest shift possible "
            "(--max-shift-px, max_shift_px)"
        )
    if coarse.lattice_by == "outside":
        return (
            f"beyond the bound: the shifts the images fit alike, "
            f"{format_shifts(coarse.candidates_px)} px (lattice translations of a periodic "
            "sample), all lie beyond max_shift_px; the frames moved farther than stated"
        )
    return (
        f"ambiguous: the images cannot tell apart the shifts {format_shifts(coarse.candidates_px)}"
        " px (lattice translations of a periodic sample: the content fits each as well), "
        "and no expected drift decides; give it (--prior-px DX DY on the command line, "
        "prior_px in the API), or the largest shift possible (--max-shift-px, "
        "max_shift_px), or, to register the frames rather than track drift, ask for any "
        'lattice-equivalent shift (--lattice equivalent, lattice = "equivalent")'
    )


def _take_engine(shape: tuple[int, int], config: RegistrationConfig) -> BlockEngine:
    with _cache_lock:
        engine = _engines.pop((shape, config), None)
    return engine if engine is not None else BlockEngine(shape, config)


def _give_engine(engine: BlockEngine) -> None:
    with _cache_lock:
        _engines[(engine.image_shape, engine.config)] = engine
        while len(_engines) > _CACHE_SIZE:
            _engines.popitem(last=False)


def result_dtype(*images: npt.NDArray[np.floating]) -> np.dtype[np.floating]:
    """Floating dtype of the per-block arrays: that of the inputs."""
    dt: np.dtype[np.floating] = np.result_type(*images)
    return dt if dt.kind == "f" else np.dtype(np.float64)


def measure_drift(
    reference: npt.ArrayLike,
    current: npt.ArrayLike,
    *,
    pixel_size_nm: float | tuple[float, float],
    config: RegistrationConfig | None = None,
    prior_px: tuple[float, float] | None = None,
) -> DriftResult:
    """Drift of ``current`` relative to ``reference`` by block phase correlation.

    A feature at image position ``u`` in ``reference`` appears at ``u + d``
    in ``current``; x runs along columns, y along rows.

    Parameters
    ----------
    reference, current : array_like, shape (rows, cols)
        Height images in nm, both at least 64×64 and of equal shape.
    pixel_size_nm : float or (float, float)
        Pixel size, or ``(x, y)`` pixel sizes, in nm.
    config : RegistrationConfig, optional
        Engine parameters (default: ``RegistrationConfig()``).
    prior_px : (float, float), optional
        Expected drift ``(dx, dy)`` in px. Windows in ``current`` are moved by
        its rounded value, so drifts up to ``prior ± max shift`` are measured.
        On a periodic sample it decides between lattice translations that
        the content cannot tell apart (the one nearest it is measured).
        Default: the whole-image coarse alignment :func:`coarse_shift` when
        ``config.coarse`` and its peak is trusted (the block search is then
        narrowed to ±``config.coarse_search_px``), else zero.

    Returns
    -------
    DriftResult
        ``valid`` False (with ``reason``) when too few blocks agree, or when
        lattice translations tie and no prior decides (``reason`` starting
        "ambiguous", the tied shifts in ``lattice_px``).

    Raises
    ------
    InvalidFrameError
        Either image is not 2-D, too small, has NaN/Inf pixels, or is constant.
    RegistrationError
        Shapes differ, or the pixel size is not positive and finite.

    References
    ----------
    Yang, Jagannathan & Bohannan, IEEE Trans. Nanotechnology 7(2), 2008.
    """
    base = config if config is not None else RegistrationConfig()
    pixel = check_pixel_size(pixel_size_nm)
    ref = check_image(reference, "reference")
    cur = check_image(current, "current")
    if ref.shape != cur.shape:
        raise RegistrationError(
            f"reference shape {ref.shape} differs from current shape {cur.shape}"
        )
    given = check_prior(prior_px)
    shape = (int(ref.shape[0]), int(ref.shape[1]))
    cfg = config_for_image(base, ref)
    engine = _take_engine(shape, cfg)
    try:
        g_ref, ref_stats = engine.prepare(ref)
        g_cur, cur_stats = engine.prepare(cur)
        for img, grad, stats, name in ((ref, g_ref, ref_stats, "reference"),
                                       (cur, g_cur, cur_stats, "current")):  # fmt: skip
            try:
                check_frame(img, grad, stats, name, gradient=cfg.gradient)
            except NearlyBlankError as err:
                allow_nearly_blank(err, ref, cur, enabled=cfg.coarse)
        ref_spec = engine.reference(g_ref)
        found = register(
            engine, ref_spec, g_cur, cur, ref_heights=ref, expected_px=given,
            source="given", pixel_size_nm=pixel,
        )  # fmt: skip
        refused: DriftResult | None = None
        for coarse in (found.coarse, found.alternative):
            if (
                not found.result.valid
                and coarse is not None
                and coarse.trusted
                and (
                    engine.placed_fraction(ref_spec, coarse.prior_px) * engine.layout.n_blocks
                    < cfg.min_valid_blocks
                    or _windows_clipped(coarse, engine)
                )
            ):
                small = _measure_overlap(ref, cur, coarse, base, pixel)
                if small is not None:
                    small = check_bound(small, cfg.max_shift_px, pixel)
                if small is not None and small.valid:
                    return small
                refused = refused or small
    finally:
        _give_engine(engine)
    return refused or found.result


def _windows_clipped(coarse: CoarseShift, engine: BlockEngine) -> bool:
    """Whether the coarse shift leaves less overlap on an axis than one
    extended window: the block windows are then clamped into an overlap
    they do not fit (a 450² pair 350 px apart overlaps 100 rows, less than
    a 128 px window), and their peaks lie at the edge of their search."""
    ext_y, ext_x = engine.layout.ext
    rows, cols = engine.image_shape
    return rows - abs(coarse.dy_px) < ext_y or cols - abs(coarse.dx_px) < ext_x


def _measure_overlap(
    ref: npt.NDArray[np.floating],
    cur: npt.NDArray[np.floating],
    coarse: CoarseShift,
    config: RegistrationConfig,
    pixel: tuple[float, float],
) -> DriftResult | None:
    """A shift so large that too few block windows fit the overlap: measure
    the overlapping parts (cut at the coarse integer shift) against each
    other, with blocks sized for them, and add the shift back. None when the
    overlap is smaller than :data:`MIN_IMAGE_PX` on an axis."""
    dx, dy = int(coarse.dx_px), int(coarse.dy_px)
    rows, cols = ref.shape
    if rows - abs(dy) < MIN_IMAGE_PX or cols - abs(dx) < MIN_IMAGE_PX:
        return None
    (ra, ca), (rb, cb) = overlap_slices(ref.shape, dx, dy)
    inner = measure_drift(
        ref[ra, ca], cur[rb, cb], pixel_size_nm=pixel, config=config, prior_px=(0.0, 0.0)
    )
    f = inner.field
    offset = np.array([ca.start, ra.start], dtype=f.centres_px.dtype)
    field = replace(
        f, centres_px=f.centres_px + offset, weight_centres_px=f.weight_centres_px + offset
    )
    how = f"overlap of {rows - abs(dy)}×{cols - abs(dx)} px at the {coarse.describe()}"
    if not inner.valid:
        return replace(inner, field=field, prior_px=(float(dx), float(dy)), prior=how)
    px, py = pixel
    return replace(
        inner,
        dx_px=inner.dx_px + dx,
        dy_px=inner.dy_px + dy,
        dx_nm=(inner.dx_px + dx) * px,
        dy_nm=(inner.dy_px + dy) * py,
        field=replace(field, vectors_px=f.vectors_px + np.array([dx, dy], f.vectors_px.dtype)),
        prior_px=(float(dx), float(dy)),
        prior=how,
    )


def measure_blocks(
    engine: BlockEngine,
    ref: ReferenceSpectra,
    grad: npt.NDArray[np.float32],
    *,
    prior_px: tuple[float, float],
    search_px: float | None = None,
    heights: npt.NDArray[np.floating] | None = None,
    check: Callable[[FrameStats], None] | None = None,
) -> tuple[BlockMeasurement, npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Block pass around ``prior_px``, repeated once around the measured
    drift when that is more than ``REFINE_PX`` away (``config.refine``):
    windows then sit within half a pixel of their content, where the
    window-envelope correction of the sub-pixel estimate is most exact and
    no content is lost at the window edges. ``search_px`` narrows the peak
    search; ``heights`` and ``check``: a new frame whose gradient image the
    first pass computes into ``grad`` (see :meth:`BlockEngine.measure`)."""
    meas, top, left = engine.measure(
        ref, grad, prior_px=prior_px, search_px=search_px, heights=heights, check=check
    )
    if not engine.config.refine:
        return meas, top, left
    if meas.n_measured < engine.config.min_valid_blocks:
        return meas, top, left
    again = meas.median_px
    if max(abs(again[0] - prior_px[0]), abs(again[1] - prior_px[1])) > REFINE_PX:
        meas, top, left = engine.measure(ref, grad, prior_px=again, search_px=search_px)
    return meas, top, left


def warm_up(config: RegistrationConfig | None = None) -> float:
    """Make the engine's compiled kernels ready in this process; returns the
    seconds it took.

    Numba compiles the kernels on their first call (about 10 s after an
    install, while its on-disk cache is empty; about 0.5 s to load them
    from the cache later), holding the GIL meanwhile. This measures a small
    synthetic pair, in float32 and float64 (the dtypes frames come in), with
    each pre-filter ``gradient = "auto"`` can pick for an image
    (:func:`~afmdrift.registration._blocks.choose_prefilter`), so that the
    first real frame does not pay it: call it where a pause is harmless, as
    the drift service does before it starts publishing.
    """
    cfg = config if config is not None else RegistrationConfig()
    start = time.perf_counter()
    rng = np.random.default_rng(0)
    base = rng.standard_normal((264, 264))
    # The pair is white noise, for which "auto" picks the levelled heights;
    # a smooth texture gets the compiled x-gradient pass.
    gradients = ("x", "levelled") if cfg.gradient == "auto" else (cfg.gradient,)
    for gradient in gradients:
        each = cfg.model_copy(update={"gradient": gradient})
        for dtype in (np.float32, np.float64):
            ref = base[4:260, 4:260].astype(dtype)
            cur = base[2:258, 5:261].astype(dtype)  # a shift of (1, 2) px
            result = measure_drift(ref, cur, pixel_size_nm=1.0, config=each, prior_px=(0.0, 0.0))
            # what the position component reads of every measured frame
            result.field.valid_row_means_px()
            result.field.valid_mean_std_px(ddof=0)
    return time.perf_counter() - start

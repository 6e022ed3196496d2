"""Streaming registration: :class:`DriftTracker` and :class:`TrackStep`.

Reference modes (``RegistrationConfig.reference``)
--------------------------------------------------
``"consecutive"``
    Each frame is measured against the previous accepted frame, whose block
    spectra are reused (no extra FFT when its windows sat on the grid: they
    stay there while the expected motion per frame is within 2 px).
    Cumulative drift is a sum of increments, so its error random-walks.
``"keyframe"`` (default)
    Frames are measured against a keyframe until the overlap between the
    keyframe and the current frame falls below ``keyframe_min_overlap``; the
    current frame then becomes the keyframe. The overlap is the smaller of the
    shared area ``(1 - |dx|/W)(1 - |dy|/H)`` and the share of blocks whose
    windows still fit the frame at that drift (in small frames the windows,
    half the frame wide, run out long before the area does).
    Errors only accumulate at re-anchoring, not at every frame.

In both modes the block windows of the new frame are placed at the expected
drift (last position plus the last increment per frame), so a steady drift
does not eat into the search range.

Invalid input and invalid measurements
--------------------------------------
A frame that raises a typed error (NaN pixels, wrong shape, different pixel
size, no texture) leaves the tracker exactly as it was. A measurement that
comes out invalid (too few agreeing blocks) is reported in the returned
:class:`TrackStep` with ``accepted=False``; the reference, the position and
the prediction are kept, the frame is skipped, and the next frame is
measured against the same reference with the prediction extrapolated over
the skipped frame. Before giving up on a frame, the tracker retries once
from the whole-image coarse alignment (:func:`coarse_shift`, when trusted
and ``config.coarse``); the first frame after the reference, whose motion
is not known yet, starts from it, as :func:`measure_drift` does.
"""

from __future__ import annotations

import functools
import math
import statistics
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import RegistrationConfig
from afmdrift.errors import InputError
from afmdrift.registration._blocks import FrameStats, config_for_image
from afmdrift.registration._checks import (
    allow_nearly_blank,
    check_frame,
    check_image,
    check_pixel_size,
    check_prior,
)
from afmdrift.registration._engine import BlockEngine, ReferenceSpectra
from afmdrift.registration._errors import NearlyBlankError, RegistrationError
from afmdrift.registration._measure import (
    REFINE_PX,
    invalid_result,
    reference_repeats,
    register,
)
from afmdrift.registration._result import DriftResult

if TYPE_CHECKING:
    from afmdrift.records import Frame

__all__ = ["HOLD_K", "HOLD_MIN_PX", "DriftTracker", "TrackStep"]

#: A step farther than max(HOLD_MIN_PX, HOLD_K · robust spread of the recent
#: prediction errors) from the predicted position is held until the next frame
#: confirms it (px).
HOLD_MIN_PX = 8.0
HOLD_K = 6.0
#: Recent prediction errors kept for that spread.
_INNOVATIONS_KEPT = 8


@dataclass(frozen=True, eq=False)
class TrackStep:
    """What :meth:`DriftTracker.update` learnt from one frame.

    Attributes
    ----------
    frame_index : int
        Number of the frame among those given to the tracker (first is 0).
    increment : DriftResult
        Drift since the previous accepted frame (its ``field`` vectors are
        relative to that frame too).
    measurement : DriftResult
        The raw measurement against the reference frame ``reference_index``.
    reference_index : int
        Frame the measurement was made against.
    keyframe_index : int
        Current keyframe after this step (consecutive mode: the reference).
    position_px, position_nm : (float, float)
        Cumulative drift ``(x, y)`` since the first frame of the last accepted
        frame (unchanged when this frame was not accepted).
    accepted : bool
        The measurement was valid and moved the tracker on.
    reanchored : bool
        This frame became the new keyframe.
    """

    frame_index: int
    increment: DriftResult
    measurement: DriftResult
    reference_index: int
    keyframe_index: int
    position_px: tuple[float, float]
    position_nm: tuple[float, float]
    accepted: bool
    reanchored: bool


class DriftTracker:
    """Measure drift frame after frame with cached reference spectra.

    Parameters
    ----------
    pixel_size_nm : float or (float, float)
        Pixel size, or ``(x, y)`` pixel sizes, in nm; every frame must match.
    config : RegistrationConfig, optional

    Examples
    --------
    >>> tracker = DriftTracker(pixel_size_nm=2.0)          # doctest: +SKIP
    >>> for image in images:                              # doctest: +SKIP
    ...     step = tracker.update(image)
    ...     if step is not None and step.accepted:
    ...         print(step.position_nm)
    """

    def __init__(
        self,
        *,
        pixel_size_nm: float | tuple[float, float],
        config: RegistrationConfig | None = None,
    ) -> None:
        self.config = config if config is not None else RegistrationConfig()
        self.pixel_size_nm = check_pixel_size(pixel_size_nm)
        self._engine: BlockEngine | None = None
        self.reset()

    def reset(self) -> None:
        """Forget all frames; the next frame becomes the first reference.

        The FFT plans of the current frame shape are kept.
        """
        self._ref: ReferenceSpectra | None = None
        self._ref_heights: npt.NDArray[np.float32] | None = None
        self._motion_known = False  # True once a frame was accepted
        self._spare: npt.NDArray[np.float32] | None = None
        self._count = 0
        self._ref_index = 0
        # (x, y) pairs as Python floats (a few scalar operations per frame,
        # cheaper than NumPy's on two-element arrays):
        self._ref_pos = (0.0, 0.0)  # cumulative position of the reference, px
        self._rel = (0.0, 0.0)  # last accepted frame relative to the reference, px
        self._rel_sigma_nm = (0.0, 0.0)
        self._velocity = (0.0, 0.0)  # last increment per frame, px
        self._last_index = 0
        self._innovations: deque[float] = deque(maxlen=_INNOVATIONS_KEPT)
        self._given: tuple[float, float] | None = None  # expect(): until a frame is accepted
        # a held frame: (index, its measurement against the current reference)
        # and how far it landed from the prediction
        self._held: tuple[int, tuple[float, float], tuple[float, float]] | None = None
        # the frame given to measure_ahead and its heights as measured (a
        # plain view of an array subclass, such as a memory-mapped stack's
        # frame), so that the update for it measures the same object
        self._ahead_heights: tuple[Any, npt.NDArray[np.floating]] | None = None

    @property
    def frames_seen(self) -> int:
        """Frames given to :meth:`update` that passed the input checks."""
        return self._count

    @property
    def keyframe_index(self) -> int:
        """Index (among the frames given) of the frame new frames are measured against."""
        return self._ref_index

    @property
    def block_rows_px(self) -> npt.NDArray[np.float64]:
        """Distinct rows of the block centres, px (empty before the first frame)."""
        if self._engine is None:
            return np.zeros(0)
        return self._engine.block_rows_px

    @property
    def position_px(self) -> tuple[float, float]:
        """Cumulative drift ``(x, y)`` of the last accepted frame, px."""
        return self._ref_pos[0] + self._rel[0], self._ref_pos[1] + self._rel[1]

    def update(
        self, image: npt.ArrayLike | Frame, *, moved_px: tuple[float, float] = (0.0, 0.0)
    ) -> TrackStep | None:
        """Register a new frame.

        Parameters
        ----------
        image : array_like, shape (rows, cols), or Frame
            Height image in nm. A :class:`~afmdrift.drivers.Frame` is checked
            for the tracker's pixel size.
        moved_px : (float, float), optional
            Known motion of the image content ``(dx, dy)`` since the last
            accepted frame that is not drift, px: a commanded offset move of
            +Δ moves content by −Δ. It is added to the expected position where
            the block windows are placed (so a move of many pixels does not
            leave the search range) and kept out of the drift velocity.

        Returns
        -------
        TrackStep or None
            None for the first frame, which becomes the reference.

        Raises
        ------
        InvalidFrameError, RegistrationError
            Unusable image, or shape/pixel size different from the first
            frame; the tracker state is unchanged.
        """
        heights = self._heights(image)
        self._ahead_heights = None
        shape = (int(heights.shape[0]), int(heights.shape[1]))
        if (
            self._ref is not None
            and self._engine is not None
            and (shape != self._engine.image_shape)
        ):
            raise RegistrationError(
                f"frame shape {shape} differs from the tracked shape "
                f"{self._engine.image_shape}; call reset() to start over"
            )
        engine = self._engine_for(heights)
        grad = self._gradient_buffer(engine)
        if self._ref is None:
            self._check(heights, grad, engine.prepare(heights, out=grad)[1])
            self._ref = engine.reference(grad)
            self._ref_heights = heights.astype(np.float32)
            self._ref_index = self._count
            self._last_index = self._count
            self._count += 1
            return None
        moved = check_prior(moved_px)
        assert moved is not None
        return self._step(engine, self._ref, grad, heights, moved)

    def expect(self, prior_px: tuple[float, float] | None) -> None:
        """Expected drift ``(dx, dy)`` of the next frames relative to the
        reference, px, given by the user (``--prior-px``): it centres the
        block search (and, on a periodic sample, picks the lattice
        translation nearest it) until a frame is accepted; from then on the
        tracker's own prediction does. None forgets it. :meth:`reset`
        forgets it too.

        Raises
        ------
        InputError
            ``prior_px`` is not two finite numbers.
        """
        self._given = check_prior(prior_px)

    def measure_ahead(
        self, image: npt.ArrayLike | Frame, *, moved_px: tuple[float, float] = (0.0, 0.0)
    ) -> bool:
        """Start registering the frame the next :meth:`update` will be given,
        and return while the engine's workers measure its blocks without the
        GIL: a caller with frames in hand (a stack, a movie) runs its own
        Python for the frame before meanwhile.

        The next :meth:`update` with the same array (the same object) and
        ``moved_px`` completes the pass and gives what it would have given
        without it; any other call drops the pass. Nothing is started (False
        is returned) for the first frame, for a frame the checks refuse (the
        update refuses it), for heights that are not a float array (each
        call converts them anew; a float array subclass, such as a frame of
        a memory-mapped stack, is measured as a plain view of it, the same
        for both calls), and where the coarse alignment must come
        first (no motion known yet, or a reference that repeats itself, whose
        lattice translation it decides). Call :meth:`finish_ahead` before leaving the
        tracker alone for long: it completes the pass on the calling thread
        too, so that no worker runs on.
        """
        engine, ref = self._engine, self._ref
        if engine is None or ref is None:
            return False
        try:
            heights = self._heights(image)
            moved = check_prior(moved_px)
        except InputError:
            return False
        given = image.heights_nm if hasattr(image, "heights_nm") else image
        if heights is not given and heights.base is not given:
            # converted (not a float array): the update converts it anew, and
            # a pass on this copy would never be the one it asks for
            return False
        if moved is None or heights.shape != engine.image_shape:
            return False
        expected = self._expected(moved)[1]
        if expected is None:
            return False
        if (
            self.config.coarse
            and self._ref_heights is not None
            and reference_repeats(ref, self._ref_heights)
        ):
            return False  # a lattice: the coarse alignment decides the translation first
        grad = self._gradient_buffer(engine)
        started = engine.measure_ahead(
            ref,
            grad,
            prior_px=expected,
            heights=heights,
            check=functools.partial(self._check, heights, grad),
        )
        self._ahead_heights = (given, heights) if started else None
        return started

    def finish_ahead(self) -> None:
        """Complete a pass started by :meth:`measure_ahead` (on the calling
        thread too) and keep it for the :meth:`update` it is for."""
        if self._engine is not None:
            self._engine.finish_ahead()

    # -- internals ---------------------------------------------------------------

    def _gradient_buffer(self, engine: BlockEngine) -> npt.NDArray[np.float32]:
        """The array the next frame's gradient image goes into: the last
        frame's, unless that frame became the reference (which keeps its
        gradient image)."""
        spare = self._spare
        if (
            spare is None
            or spare.shape != engine.layout.grad_shape
            or (self._ref is not None and spare is self._ref.grad)
        ):
            spare = np.empty(engine.layout.grad_shape, np.float32)
        self._spare = spare
        return spare

    def _expected(
        self, moved: tuple[float, float]
    ) -> tuple[tuple[float, float], tuple[float, float] | None, bool]:
        """For the next frame: the predicted position relative to the
        reference (px), where its windows go (None: not known, the coarse
        alignment decides), and whether any motion is known."""
        cfg = self.config
        gap = self._count - self._last_index
        given = None if self._motion_known else self._given
        if given is not None:
            # the user's expectation stands for the motion not known yet
            # (not a prediction from measured motion: nothing is held against it)
            prior = (given[0] + moved[0], given[1] + moved[1])
            return prior, prior, moved != (0.0, 0.0)
        prior = (
            self._rel[0] + self._velocity[0] * gap + moved[0],
            self._rel[1] + self._velocity[1] * gap + moved[1],
        )
        motion_known = self._motion_known or moved != (0.0, 0.0)
        expected: tuple[float, float] | None = prior if motion_known else None
        if (
            expected is not None
            and cfg.reference == "consecutive"
            and max(abs(prior[0]), abs(prior[1])) <= REFINE_PX
        ):
            # Small expected motion: leave the windows on the grid, so that
            # this frame's spectra can serve as the next reference unchanged.
            expected = (0.0, 0.0)
        return prior, expected, motion_known

    def _heights(self, image: Any) -> npt.NDArray[np.floating]:
        if hasattr(image, "heights_nm") and hasattr(image, "pixel_size_nm"):
            frame_px = check_pixel_size(image.pixel_size_nm)
            if not np.allclose(frame_px, self.pixel_size_nm, rtol=1e-9, atol=0.0):
                raise RegistrationError(
                    f"frame pixel size {frame_px} nm differs from the tracker's "
                    f"{self.pixel_size_nm} nm"
                )
            image = image.heights_nm
        ahead = self._ahead_heights
        if ahead is not None and ahead[0] is image:
            return ahead[1]  # checked by measure_ahead, a view of this very array
        return check_image(image, "frame")  # its values: see update

    def _check(
        self, heights: npt.NDArray[np.floating], grad: npt.NDArray[np.float32], stats: FrameStats
    ) -> None:
        """Refuse an unusable frame (:func:`check_frame`); the tracker is
        unchanged then. A nearly blank frame is kept when it locks strongly
        onto the reference (:func:`allow_nearly_blank`)."""
        try:
            gradient = (
                self.config.gradient if self._engine is None else self._engine.config.gradient
            )
            check_frame(heights, grad, stats, "frame", gradient=gradient)
        except NearlyBlankError as err:
            allow_nearly_blank(err, self._ref_heights, heights, enabled=self.config.coarse)

    def _gradient(self) -> str:
        return self.config.gradient if self._engine is None else self._engine.prefilter

    def _engine_for(self, heights: npt.NDArray[np.floating]) -> BlockEngine:
        """The engine of the stream: made for its first frame (block sizes for
        the shape, the pre-filter chosen from its data), and kept, with its FFT
        plans, while later streams need the same."""
        shape = (int(heights.shape[0]), int(heights.shape[1]))
        if self._engine is not None and self._engine.image_shape == shape and self._ref is not None:
            return self._engine
        cfg = config_for_image(self.config, heights)
        if self._engine is None or self._engine.config != cfg:
            self._engine = BlockEngine(shape, cfg)
        return self._engine

    def _step(
        self,
        engine: BlockEngine,
        ref: ReferenceSpectra,
        grad: npt.NDArray[np.float32],
        heights: npt.NDArray[np.floating],
        moved: tuple[float, float],
    ) -> TrackStep:
        cfg = self.config
        index = self._count
        gap = index - self._last_index
        prior, expected, motion_known = self._expected(moved)
        found = register(
            engine,
            ref,
            grad,
            heights,
            ref_heights=self._ref_heights if cfg.coarse else None,
            expected_px=expected,
            source="given" if self._given is not None and not self._motion_known else "predicted",
            pixel_size_nm=self.pixel_size_nm,
            check=functools.partial(self._check, heights, grad),
            miss_px=self._miss_spread_px() if motion_known else 0.0,
        )
        meas, top, left = found.result, found.top, found.left
        if meas.valid and motion_known and moved == (0.0, 0.0):
            meas, jump = self._confirm(meas, prior, index)
            # a confirmed jump is no drift: kept out of the velocity, as a move is
            moved = (moved[0] + jump[0], moved[1] + jump[1])
        self._count += 1
        ref_index = self._ref_index
        increment = self._increment(meas)
        reanchor = False
        if meas.valid:
            reanchor = self._accept(engine, ref, grad, meas, index, gap, top, left, moved)
            self._motion_known = True
            if reanchor:
                # Kept (as float32) for the coarse retry of later frames.
                self._ref_heights = heights.astype(np.float32)
        pos = self.position_px
        return TrackStep(
            frame_index=index,
            increment=increment,
            measurement=meas,
            reference_index=ref_index,
            keyframe_index=self._ref_index,
            position_px=pos,
            position_nm=self._to_nm(pos),
            accepted=meas.valid,
            reanchored=reanchor and cfg.reference == "keyframe",
        )

    def _miss_spread_px(self) -> float:
        """Robust spread of the recent prediction misses, px (0 before three)."""
        if len(self._innovations) < 3:
            return 0.0
        return 1.4826 * float(statistics.median(self._innovations))

    def hold_limit_px(self) -> float:
        """Farthest a step may land from the predicted position and be accepted
        at once, px: ``max(floor, HOLD_K · 1.4826 · median |error|)`` over the
        recent prediction errors, the floor being the larger of
        :data:`HOLD_MIN_PX` and half the block search radius (a drift that
        changes speed between frames, an air-conditioning cycle sampled every
        256 s, misses a constant-velocity prediction by several px)."""
        floor = HOLD_MIN_PX
        if self._engine is not None:
            floor = max(floor, 0.5 * float(min(self._engine.layout.max_shift)))
        return max(floor, HOLD_K * self._miss_spread_px())

    def _confirm(
        self, meas: DriftResult, prior: tuple[float, float], index: int
    ) -> tuple[DriftResult, tuple[float, float]]:
        """Tracker confirmation: a valid measurement far from the predicted
        position ``prior`` (a registration mis-lock on a streaked frame, or a
        real jump such as a tip change) is held, returned as invalid, and
        accepted only when the next frame lands where the jump predicts.
        Returns the result and the confirmed jump (zero if none)."""
        limit = self.hold_limit_px()
        error = math.hypot(meas.dx_px - prior[0], meas.dy_px - prior[1])
        # every valid measurement's error enters the (median) spread, so a
        # drift that is hard to predict widens the limit; a lone mis-lock
        # barely moves the median
        self._innovations.append(error)
        held, self._held = self._held, None
        if error <= limit:
            return meas, (0.0, 0.0)
        if held is not None:
            h_index, (hx, hy), jump_px = held
            steps = index - h_index
            jump = (hx + self._velocity[0] * steps, hy + self._velocity[1] * steps)
            if math.hypot(meas.dx_px - jump[0], meas.dy_px - jump[1]) <= limit:
                note = f"{meas.prior}; confirms the jump held at frame {h_index}"
                return replace(meas, prior=note), jump_px
        jump_now = (meas.dx_px - prior[0], meas.dy_px - prior[1])
        self._held = (index, (meas.dx_px, meas.dy_px), jump_now)
        held_result = replace(
            invalid_result(
                meas.field,
                f"held: {error:.1f} px from the predicted position (more than the "
                f"{limit:.1f} px this track allows); accepted if the next frame confirms it",
                valid_blocks=meas.valid_blocks,
            ),
            prior_px=meas.prior_px,
            prior=meas.prior,
            lattice_px=meas.lattice_px,
        )
        return held_result, (0.0, 0.0)

    def _accept(
        self,
        engine: BlockEngine,
        ref: ReferenceSpectra,
        grad: npt.NDArray[np.float32],
        meas: DriftResult,
        index: int,
        gap: int,
        top: npt.NDArray[np.intp],
        left: npt.NDArray[np.intp],
        moved: tuple[float, float],
    ) -> bool:
        """Move the tracker on to a validly measured frame; True if it became
        the new reference."""
        cfg = self.config
        rel = (meas.dx_px, meas.dy_px)
        self._velocity = (
            (rel[0] - self._rel[0] - moved[0]) / gap,
            (rel[1] - self._rel[1] - moved[1]) / gap,
        )
        self._rel = rel
        self._rel_sigma_nm = (meas.sigma_x_nm, meas.sigma_y_nm)
        self._last_index = index
        reanchor = cfg.reference == "consecutive" or self._overlap(engine, ref, rel) < (
            cfg.keyframe_min_overlap
        )
        if reanchor:
            grid_top, grid_left = engine.grid_positions()
            if np.array_equal(top, grid_top) and np.array_equal(left, grid_left):
                self._ref = engine.current_as_reference(grad, top, left)
            else:
                self._ref = engine.reference(grad)
            if "repeats" in ref.derived:
                # A sample does not turn into a lattice (or out of one) from a
                # frame to the next: the stream's first reference decides it,
                # so that consecutive mode does not pay the search per frame.
                self._ref.derived["repeats"] = ref.derived["repeats"]
            self._ref_index = index
            self._ref_pos = (self._ref_pos[0] + rel[0], self._ref_pos[1] + rel[1])
            self._rel = (0.0, 0.0)
            self._rel_sigma_nm = (0.0, 0.0)
        return reanchor

    def _increment(self, meas: DriftResult) -> DriftResult:
        """The measurement re-expressed relative to the previous accepted frame."""
        px, py = self.pixel_size_nm
        prev = self._rel
        f = meas.field
        field = replace(f, vectors_px=f.vectors_px - np.array(prev, dtype=f.vectors_px.dtype))
        sx = math.hypot(meas.sigma_x_nm, self._rel_sigma_nm[0])
        sy = math.hypot(meas.sigma_y_nm, self._rel_sigma_nm[1])
        dx = meas.dx_px - prev[0]
        dy = meas.dy_px - prev[1]

        def rel(v: tuple[float, float] | None) -> tuple[float, float] | None:
            return None if v is None else (v[0] - prev[0], v[1] - prev[1])

        # what decided it and the search's centre come along, re-expressed
        # relative to the previous accepted frame as the shift is
        return replace(
            meas,
            dx_px=dx,
            dy_px=dy,
            dx_nm=dx * px,
            dy_nm=dy * py,
            sigma_x_nm=sx,
            sigma_y_nm=sy,
            sigma_nm=math.sqrt(0.5 * (sx * sx + sy * sy)),
            field=field,
            prior_px=rel(meas.prior_px),
            expected_px=rel(meas.expected_px),
            alternatives_px=tuple((a - prev[0], b - prev[1]) for a, b in meas.alternatives_px),
        )

    def _overlap(
        self, engine: BlockEngine, ref: ReferenceSpectra, rel: tuple[float, float]
    ) -> float:
        """Smaller of the shared area fraction and the fraction of blocks whose
        windows still fit the frame at drift ``rel`` from the keyframe."""
        rows, cols = engine.image_shape
        area = max(0.0, 1.0 - abs(rel[0]) / cols) * max(0.0, 1.0 - abs(rel[1]) / rows)
        return min(area, engine.placed_fraction(ref, rel))

    def _to_nm(self, pos: tuple[float, float]) -> tuple[float, float]:
        return pos[0] * self.pixel_size_nm[0], pos[1] * self.pixel_size_nm[1]

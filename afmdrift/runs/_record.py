"""One frame, start to finish: pipeline, then one store transaction; and the
frames a store could not write yet (a full disk), held until it can.

:func:`record_outcome` is the one way a processed frame reaches the store:
``afmdrift replay`` calls it for each frame, and the daemon's
:class:`HeldWrites` calls it for each frame it holds, so both record exactly
the same rows.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import json
import logging
import sqlite3
import sys
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.model import FrameTrajectory
from afmdrift.pipeline import FrameOutcome, FramePipeline, FrameRecord
from afmdrift.records import ChannelSample, Event, Frame, LoggedEvent
from afmdrift.runs._changes import ModelChange
from afmdrift.runs._schema import StoreError
from afmdrift.runs._store import UNSTORED_KEY, RunStore, SeqRanges

__all__ = ["HeldWrites", "process_and_record", "record_outcome"]

log = logging.getLogger(__name__)

#: What a failed store write raises: SQLite (disk full, I/O error, read-only
#: file) or the file system (an image or CSV file on a full disk).
STORE_WRITE_ERRORS = (sqlite3.Error, OSError)


def process_and_record(
    pipeline: FramePipeline,
    store: RunStore,
    frame: Frame,
    *,
    channels: Iterable[ChannelSample] = (),
    events: Iterable[Event | LoggedEvent] = (),
    seq: int,
    epoch: int = 0,
    detected_wall_s: float | None = None,
    t_now_s: float | None = None,
    hold: str | None = None,
) -> FrameOutcome:
    """Process ``frame`` and commit it, with what reached the model's history, at once.

    ``channels`` and ``events`` are entries that became known since the
    previous call; the ones logged up to the end of the frame reach the model
    with it and are committed in the frame's transaction, later ones wait for
    the next frame. (The daemon does the same through :class:`HeldWrites`, so
    that a store that cannot write does not stop it.)
    """
    pipeline.push(channels, events)
    outcome = pipeline.process(
        frame,
        seq=seq,
        epoch=epoch,
        detected_wall_s=detected_wall_s,
        t_now_s=t_now_s,
        hold=hold,
    )
    record_outcome(store, outcome)
    return outcome


def record_outcome(store: RunStore, outcome: FrameOutcome) -> None:
    """Commit a processed frame with what reached the model's history with it.

    :func:`process_and_record`, ``afmdrift replay`` (over
    :meth:`FramePipeline.run`) and the daemon (:class:`HeldWrites`) all end
    each frame here, so a replayed session is recorded exactly as the daemon
    records it. All or nothing (:meth:`RunStore.record_frame`).
    """
    _Held.of(outcome, archive=True).write(store)


def give_back_memory() -> None:
    """Return heap memory freed by written frames to the system.

    The frames held through a store outage are freed once written, but glibc
    keeps freed heap chunks for reuse: the daemon's resident memory stayed
    7, 6 and 3 MiB higher after each of the three disk-full episodes of the
    week-long soak (flat between them). ``malloc_trim`` hands them back; on
    other C libraries and systems this does nothing."""
    gc.collect()
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return
    trim(0)


@dataclass(slots=True)
class _Held:
    """What :meth:`RunStore.record_frame` needs of one frame; images and older
    model states can be let go while it waits."""

    record: FrameRecord
    predictor: str
    #: The model state and curve; JSON text once the frame waits (one block
    #: of memory each, which a trimmed heap gives back, instead of thousands
    #: of small objects whose arenas stay: the soak's daemon kept 6-7 % more
    #: resident memory after three disk-full episodes).
    state: dict[str, Any] | str | None
    curve: dict[str, Any] | str | None
    image: npt.NDArray[np.floating] | None
    reference: npt.NDArray[np.floating] | None
    trajectory: FrameTrajectory | None
    corrected: npt.NDArray[np.floating] | None
    channels: list[ChannelSample] = field(default_factory=list)
    events: list[LoggedEvent] = field(default_factory=list)
    #: The model state's size once serialised (measured when first held).
    state_bytes: int = 0

    @classmethod
    def of(cls, outcome: FrameOutcome, *, archive: bool) -> _Held:
        has_state = outcome.predictor_state is not None
        return cls(
            record=outcome.record,
            predictor=outcome.predictor_name,
            state=outcome.predictor_state,
            curve=outcome.curve_dict if has_state else None,
            # the store writes the image only when it archives frames
            image=outcome.image if archive else None,
            reference=outcome.reference,
            trajectory=outcome.trajectory,
            corrected=outcome.corrected,
            channels=list(outcome.history.channels),
            events=[LoggedEvent(*e) for e in outcome.history.events],
        )

    def write(self, store: RunStore, meta: dict[str, str] | None = None) -> None:
        store.record_frame(
            self.record,
            predictor=self.predictor,
            predictor_state=self.state,
            curve=self.curve,
            image=self.image,
            reference=self.reference,
            trajectory=self.trajectory,
            corrected=self.corrected,
            channels=self.channels,
            events=self.events,
            meta=meta,
        )

    def image_bytes(self) -> int:
        return sum(a.nbytes for a in (self.image, self.reference, self.corrected) if a is not None)

    def nbytes(self) -> int:
        """Memory this frame holds, roughly (images, model state, rows)."""
        rows = 200 * (len(self.channels) + len(self.events))
        if self.trajectory is not None:
            rows += 48 * int(self.trajectory.t_s.size)
        return self.image_bytes() + self.state_bytes + rows + 2_000


class HeldWrites:
    """The daemon's run-store writer: a frame the store cannot write is held
    and written, in order, once the store can again.

    Every frame goes through :meth:`record`. While writes fail (no space, an
    I/O error) the daemon goes on measuring and publishing; :attr:`problem`
    names the path and the reason, and the held frames stay in memory up to
    ``max_bytes``. Past it, what is let go first is what a restart needs least:
    archived and de-warped images, then model states older than the newest
    held, then reference images older than the newest held, and only then
    whole frames, oldest first (their channels and events move on to the next
    held frame, so the logs are never dropped). Every loss is counted
    (:attr:`images_dropped`, :attr:`frames_dropped`) and logged once.

    Parameters
    ----------
    store : RunStore
        The run store; used only from the thread that calls this object.
    max_bytes : int
        Memory the held frames may take.
    archive : bool
        The store archives every image (``service.archive_frames``).
    """

    def __init__(self, store: RunStore, *, max_bytes: int, archive: bool) -> None:
        self.store = store
        self.max_bytes = max_bytes
        self.archive = archive
        self._held: deque[_Held] = deque()
        self._meta: dict[str, str] = {}
        self._bytes = 0
        #: ``"PATH: reason"`` while the store cannot write, else ``None``.
        self.problem: str | None = None
        self.images_dropped = 0
        self.frames_dropped = 0
        self.frames_written_late = 0
        self._unstored = SeqRanges.parse(store.meta().get(UNSTORED_KEY, ""))

    @property
    def held(self) -> int:
        """Frames measured but not stored yet."""
        return len(self._held)

    def set_meta(self, items: dict[str, str]) -> None:
        """Record run-level facts now, or with the next frame the store can write."""
        self._meta.update(items)
        if not self._held:
            self.flush()

    def add_model_change(self, change: ModelChange) -> None:
        """Commit a change of the run's model now, or refuse it.

        Raises
        ------
        StoreError
            The store cannot write (frames are held, or this write fails);
            nothing is committed. A change the store does not keep would not
            outlive a restart, so the caller does not make it.
        """
        if self.problem is not None or self._held:
            raise StoreError(f"the run store cannot write ({self.problem})")
        try:
            self.store.add_model_change(change)
        except (sqlite3.Error, OSError) as err:
            raise StoreError(f"{self.store.path}: the run store cannot write ({err})") from None

    def record(self, outcome: FrameOutcome) -> None:
        """Write this frame (after any held ones); hold it if the store cannot."""
        h = _Held.of(outcome, archive=self.archive)
        self._held.append(h)
        self._bytes += h.nbytes()
        if self.flush():
            return
        if h.state is not None:  # serialised only for a frame that waits
            h.state = json.dumps(h.state) if isinstance(h.state, dict) else h.state
            if isinstance(h.curve, dict):
                h.curve = json.dumps(h.curve)
            h.state_bytes = len(h.state)
            self._bytes += h.state_bytes
        self._bound()

    def flush(self) -> bool:
        """Write what is held, oldest first; True once nothing is held."""
        try:
            if self._meta:
                if self._held:
                    self._held[0].write(self.store, self._meta)
                    self._written()
                else:
                    self.store.set_meta(self._meta)
                self._meta = {}
            while self._held:
                self._held[0].write(self.store)
                self._written()
        except sqlite3.IntegrityError as err:
            # Not a full disk: a frame the store already has. Never retried.
            dup = self._held.popleft()
            self._bytes -= dup.nbytes()
            log.error("run store: frame %d not written (%s)", dup.record.seq, err)
            return self.flush()
        except STORE_WRITE_ERRORS as err:
            self._failed(err)
            return False
        if self.problem is not None:
            log.warning(
                "run store %s writes again: %d held frame(s) written; %d frame(s) and %d "
                "image(s) were not stored",
                self.store.path, self.frames_written_late, self.frames_dropped,
                self.images_dropped,
            )  # fmt: skip
            self.problem = None
            give_back_memory()
        self._bytes = 0
        return True

    def _written(self) -> None:
        done = self._held.popleft()
        self._bytes -= done.nbytes()
        if self.problem is not None:
            self.frames_written_late += 1

    def _failed(self, err: BaseException) -> None:
        problem = f"{self.store.path}: {err}"
        if self.problem is None:
            log.error(
                "run store cannot write (%s): the daemon goes on measuring and publishing, "
                "and holds up to %.0f MB of frames to write when it can",
                problem, self.max_bytes / 1e6,
            )  # fmt: skip
        self.problem = problem

    def _bound(self) -> None:
        """Let go of what a restart needs least until the held frames fit."""
        if self._bytes <= self.max_bytes:
            return
        for h in self._held:  # archived and de-warped images
            if self._bytes <= self.max_bytes:
                return
            for name in ("image", "corrected"):
                a = getattr(h, name)
                if a is not None:
                    setattr(h, name, None)
                    self._bytes -= a.nbytes
                    self._dropped_image(h, name)
        newest_state = max((i for i, h in enumerate(self._held) if h.state), default=-1)
        newest_ref = max(
            (i for i, h in enumerate(self._held) if h.reference is not None), default=-1
        )
        for i, h in enumerate(self._held):  # older model states, then older references
            if self._bytes <= self.max_bytes:
                return
            if i < newest_state and h.state is not None:
                h.state = h.curve = None
                self._bytes -= h.state_bytes
                h.state_bytes = 0
            if i < newest_ref and h.reference is not None and self._bytes > self.max_bytes:
                self._bytes -= h.reference.nbytes
                h.reference = None
                self._dropped_image(h, "reference")
        while self._bytes > self.max_bytes and len(self._held) > 1:
            gone = self._held.popleft()
            self._bytes -= gone.nbytes()
            nxt = self._held[0]
            nxt.channels[:0] = gone.channels
            nxt.events[:0] = gone.events
            self._bytes += 200 * (len(gone.channels) + len(gone.events))
            if self.frames_dropped == 0:
                log.error(
                    "run store still cannot write and %.0f MB are held: frames are now let "
                    "go, oldest first (frame %d first; their channels and events are kept)",
                    self.max_bytes / 1e6, gone.record.seq,
                )  # fmt: skip
            self.frames_dropped += 1
            self._unstored.add(gone.record.seq)
            self._meta[UNSTORED_KEY] = self._unstored.text()

    def _dropped_image(self, h: _Held, name: str) -> None:
        if self.images_dropped == 0:
            log.warning(
                "run store still cannot write: held images are let go to stay within "
                "%.0f MB (frame %d's %s first); positions are kept",
                self.max_bytes / 1e6, h.record.seq, name,
            )  # fmt: skip
        self.images_dropped += 1

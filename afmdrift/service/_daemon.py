"""The drift daemon: small parts, wired together in one task group.

Parts, each with one job:

:class:`~afmdrift.service._link.InstrumentLink`
    connects and reconnects the instrument, starts epochs, and puts every
    instrument time on the service's time axis;
:class:`~afmdrift.service._acquire.Acquisition`
    polls frames, channels and events into one batch per frame;
:class:`~afmdrift.pipeline.FramePipeline`
    measures, predicts and rebuilds d(t) for each frame, in the worker thread
    (:class:`~afmdrift.runs.HeldWrites` commits it to the run store, or holds
    it in bounded memory while the store cannot write);
:class:`~afmdrift.service._publish.Publishing`
    the wire messages, the offset limiter, the flags and the status;
:class:`~afmdrift.service._control.Controller`
    answers the control socket (every message one reply; a token for the
    commands that change state);
:class:`~afmdrift.service._closed_loop.ClosedLoop`
    in closed loop, moves the instrument's offset along d(t).

:class:`DriftService` owns the sockets, the run store and the worker thread,
resumes from the store, and runs the loops (one :class:`asyncio.TaskGroup`;
any task that dies logs why and the group re-raises, cancelling the others;
no failure of one frame's steps ends a task: a frame whose processing fails
is reported and skipped, a store that cannot write holds the frames):
``connect``, ``clock``, ``frames``, ``channels``, ``events`` (the link and
acquisition), ``process`` (the worker), ``offset`` and ``status``
(publishing), ``control`` (the control socket) and, in closed loop,
``closed`` (applies the offset on the instrument), ``store`` (retries
writing held frames while the run store cannot write) and ``diagnosis``
(the live diagnosis of the run in a child process,
:class:`~afmdrift.service._live_diagnosis.LiveDiagnosis`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import functools
import itertools
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import zmq.asyncio

from afmdrift.config import AfmdriftConfig
from afmdrift.drivers import Instrument, VelocityActuator
from afmdrift.errors import ConfigError
from afmdrift.model import make_predictor, warm_up_effects
from afmdrift.pipeline import FrameOutcome, FramePipeline
from afmdrift.records import InstrumentInfo
from afmdrift.registration import warm_up
from afmdrift.runs import HeldWrites, ModelChange, RunStore, effective_model, model_terms
from afmdrift.service._acquire import Acquisition, FrameBatch
from afmdrift.service._closed_loop import ClosedLoop
from afmdrift.service._control import Controller
from afmdrift.service._link import INSTRUMENT_ERRORS, InstrumentLink, every
from afmdrift.service._live_diagnosis import LiveDiagnosis
from afmdrift.service._publish import OFFSET_CATCH_UP_S, Publishing
from afmdrift.service._zmq import ControlSocket, CurveKeys, Publisher, load_curve_keys
from afmdrift.wire import DiagnosisMsg, OffsetMsg, StatusMsg

__all__ = ["INSTRUMENT_ERRORS", "DriftService"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

#: While the run store cannot write, held frames are retried this often, s.
_STORE_RETRY_S = 5.0


class DriftService:
    """The drift daemon.

    Parameters
    ----------
    config : AfmdriftConfig
        Full configuration (``service``, ``registration``, ``model``).
    instrument : Instrument
        An unconnected instrument (driver, simulator client or replay).
    ctx : zmq.asyncio.Context, optional
        Context for the sockets (default: a context of its own).
    config_path : path-like, optional
        File ``reload_model`` re-reads when the request names none.
    pipeline : FramePipeline, optional
        Default: built from ``config``.

    Attributes
    ----------
    ready : asyncio.Event
        Set once the sockets are bound; :attr:`pub_endpoint` and
        :attr:`control_endpoint` then hold the bound addresses.
    """

    def __init__(
        self,
        *,
        config: AfmdriftConfig,
        instrument: Instrument,
        ctx: zmq.asyncio.Context | None = None,
        config_path: str | Path | None = None,
        pipeline: FramePipeline | None = None,
    ) -> None:
        self.config = config
        self.svc = config.service
        if (
            self.svc.closed_loop
            and self.svc.closed_loop_actuator == "velocity"
            and not isinstance(instrument, VelocityActuator)
        ):
            raise ConfigError(
                f"service.closed_loop_actuator = 'velocity' needs an instrument that can move "
                f"at a velocity (nanonis://); {type(instrument).__name__} cannot"
            )
        self.ctx = ctx
        self.config_path = Path(config_path) if config_path is not None else None
        self.pipeline = pipeline or FramePipeline(config=config)
        self.ready = asyncio.Event()
        self.pub_endpoint = ""
        self.control_endpoint = ""
        self.flags: set[str] = set()
        self.link = InstrumentLink(
            instrument, reconnect_delay_s=self.svc.reconnect_delay_s, flags=self.flags
        )
        self.acquisition = Acquisition(self.link, self.svc)
        self.publishing = Publishing(
            self.svc,
            clock=self.link.clock,
            flags=self.flags,
            epoch=lambda: self.link.epoch,
            silent_s=self.link.silent_s,
        )
        self.diagnosis = LiveDiagnosis(
            self.svc,
            effects=lambda: self.controller.config.model.physics.terms,
            config_path=lambda: self.config_path,
            publish=self._publish_diagnosis,
            run_id=self.publishing.run_id,
            epoch=lambda: self.link.epoch,
        )
        self.controller = Controller(
            config=config,
            config_path=self.config_path,
            pipeline=self.pipeline,
            publishing=self.publishing,
            in_worker=self._in_worker,
            record_change=self._record_model_change,
            diagnose=self.diagnosis.request,
        )
        self.link.on_epoch(self._new_epoch)
        self.link.on_connected(self._on_connected)
        self.link.on_instrument_changed(self._instrument_changed)
        self.frames_processed = 0
        self.latencies_s: deque[float] = deque(maxlen=1000)
        self._frame_done = asyncio.Event()
        self.closed_loop = ClosedLoop(
            self.svc,
            link=self.link,
            acquisition=self.acquisition,
            publishing=self.publishing,
            pipeline=self.pipeline,
        )
        self._store: RunStore | None = None
        self._writer: HeldWrites | None = None
        self._failures_logged: set[str] = set()
        self._control: ControlSocket | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None

    @property
    def instrument(self) -> Instrument:
        return self.link.instrument

    @property
    def last_offset(self) -> OffsetMsg | None:
        """The offset sample published last (``None`` before the first)."""
        return self.publishing.last_offset

    @property
    def instrument_errors(self) -> int:
        """Failed instrument calls so far."""
        return self.link.errors

    @property
    def frames_dropped(self) -> int:
        """Frames dropped because processing fell behind."""
        return self.acquisition.frames_dropped

    def status_msg(self) -> StatusMsg:
        """The status now (a snapshot: it takes no ``status`` sequence number)."""
        return self.publishing.status_snapshot()

    @property
    def control_token_path(self) -> Path:
        """The file holding the token state-changing control commands need."""
        return self.controller.token_path

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        """Run until cancelled; sockets, store, worker and instrument are closed on exit."""
        own_ctx = self.ctx is None
        ctx = self.ctx or zmq.asyncio.Context()
        curve_keys: CurveKeys | None = None
        publisher: Publisher | None = None
        try:
            curve_keys = load_curve_keys(self.svc)
            if curve_keys is not None:
                curve_keys.start(ctx)
            self._store = RunStore(
                self.svc.run_dir,
                archive_frames=self.svc.archive_frames,
                keep_model_states=self.svc.keep_model_states,
                check_same_thread=False,
            )
            self._writer = HeldWrites(
                self._store,
                max_bytes=int(self.svc.store_hold_mb * 1e6),
                archive=self.svc.archive_frames,
            )
            self._executor = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="afmdrift-worker"
            )
            # Compile (or load from Numba's cache) the registration kernels
            # now: on the first frame it would hold the GIL for 0.5 s (10 s
            # after an install) and stall the offset stream mid-run.
            warm_s = await self._in_worker(functools.partial(warm_up, self.config.registration))
            log.info("registration kernels ready in %.2f s", warm_s)
            # ... and the effect terms' (the play compensation runs on the loop)
            await self._in_worker(warm_up_effects)
            await self._resume_from_store()
            self.diagnosis.resume()
            publisher = Publisher(
                self.svc.pub_endpoint, ctx=ctx, sndhwm=self.svc.sndhwm, curve=curve_keys
            )
            self.publishing.publisher = publisher
            self._control = ControlSocket(
                self.svc.control_endpoint,
                ctx=ctx,
                curve=curve_keys,
                max_request_bytes=self.svc.control_max_request_bytes,
            )
            self.controller.start()
            self.pub_endpoint = publisher.endpoint
            self.control_endpoint = self._control.endpoint
            log.info(
                "drift service: publishing on %s, control on %s, run store %s",
                self.pub_endpoint,
                self.control_endpoint,
                self._store.path,
            )
            self.ready.set()
            self.link.start()
            async with asyncio.TaskGroup() as tg:
                for name, fn in self._loops().items():
                    tg.create_task(_supervised(name, fn), name=f"afmdrift-{name}")
        finally:
            self.publishing.state = "stopping"
            if self._executor is not None:
                # Let a frame in flight finish writing: the store stays consistent.
                await asyncio.shield(asyncio.to_thread(self._executor.shutdown, wait=True))
            await self.link.close()
            self.controller.stop()
            self._close_store()
            for sock in (publisher, self._control):
                if sock is not None:
                    sock.close()
            if curve_keys is not None:
                curve_keys.stop()
            if own_ctx:
                ctx.term()
            log.info("drift service stopped after %d frames", self.frames_processed)

    def _loops(self) -> dict[str, Callable[[], Awaitable[None]]]:
        svc = self.svc
        loops: dict[str, Callable[[], Awaitable[None]]] = {
            "connect": self.link.connect_loop,
            "clock": lambda: every(svc.clock_sync_interval_s, self._clock_tick),
            "frames": self.acquisition.frame_loop,
            "process": self._process_loop,
            "channels": self.acquisition.channel_loop,
            "events": self.acquisition.event_loop,
            "offset": lambda: every(
                1.0 / svc.offset_rate_hz,
                self.publishing.offset_tick,
                catch_up_s=OFFSET_CATCH_UP_S,
                skipped=self.publishing.offset_ticks_skipped,
            ),
            "status": lambda: every(svc.heartbeat_interval_s, self._status_tick),
            "control": self._serve_control,
            "store": lambda: every(_STORE_RETRY_S, self._store_retry),
            "diagnosis": self.diagnosis.loop,
        }
        if svc.closed_loop:
            loops["closed"] = lambda: every(svc.closed_loop_interval_s, self.closed_loop.tick)
        return loops

    async def _in_worker(self, fn: Callable[[], _T]) -> _T:
        assert self._executor is not None
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn)

    def _record_model_change(self, change: ModelChange) -> None:
        """Commit a change of the model to the run store (in the worker thread)."""
        assert self._writer is not None
        self._writer.add_model_change(change)

    async def _resume_from_store(self) -> None:
        assert self._store is not None
        store = self._store
        await self._in_worker(functools.partial(self._take_up_changes, store.model_changes()))
        state = store.resume_state()
        if state is None:
            return
        records = store.last_frames(max(self.svc.training_window, 1) * 2)
        logged = store.events()
        channels = store.channels()
        meta = store.meta()
        t_offset_s = float(meta.get("t_offset_s", "0"))
        await self._in_worker(
            lambda: self.pipeline.resume(state, records=records, channels=channels, events=logged)
        )
        last = state.last
        self.link.resume(
            epoch=state.epoch, t_offset_s=t_offset_s, last_seen_s=last.t_end_s,
            info=_stored_instrument(meta), pixel_size_nm=(last.pixel_x_nm, last.pixel_y_nm),
        )  # fmt: skip
        self.acquisition.resume(
            events=[e for _, _, e in logged],
            event_cursor=state.event_cursor,
            last_index=last.instrument_frame,
            last_t_end_s=last.t_end_s,
        )
        self.publishing.curve = self.pipeline.curve
        self.publishing.resume(
            frame_ends=[r.t_end_s for r in records],
            errors_nm=[r.pred_error_nm for r in records[-self.svc.rolling_window :]],
            frames=last.seq + 1,
        )
        log.info(
            "resumed run store %s after frame %d (epoch %d)", store.path, last.seq, state.epoch
        )

    def _take_up_changes(self, changes: list[ModelChange]) -> None:
        """The run's term changes on the configured model (in the worker, before
        the pipeline resumes): an added term belongs to the run."""
        model = effective_model(self.config.model, changes)
        if model == self.config.model:
            return
        self.config = self.config.model_copy(update={"model": model})
        self.controller.config = self.controller.config.model_copy(update={"model": model})
        self.pipeline.config = self.controller.config
        self.pipeline.predictor = make_predictor(model.predictor, model)
        self.publishing.terms = model_terms(model)
        log.info("the run's model changes applied: terms %s", model.physics.terms)

    # ------------------------------------------------------------------ link events

    def _on_connected(self, info: InstrumentInfo, t_s: float, offset: tuple[float, float]) -> None:
        self.publishing.connected(t_s)
        self.closed_loop.connected(t_s, offset)
        if self._writer is not None and self._executor is not None:
            ident = {f"instrument_{k}": str(v) for k, v in dataclasses.asdict(info).items()}
            self._executor.submit(self._writer.set_meta, ident)

    def _instrument_changed(self, what: str) -> None:
        # Another instrument: a new chain of positions (its references, and
        # the other geometries' of the old one, are no use), and the closed
        # loop takes the new instrument's offset as it stands.
        self.pipeline.request_reset()
        self.closed_loop.rebaseline()

    def _new_epoch(self, epoch: int, t_offset_s: float) -> None:
        self.pipeline.request_reset()
        if self._writer is not None and self._executor is not None:
            self._executor.submit(self._writer.set_meta, {"t_offset_s": repr(t_offset_s)})

    async def _clock_tick(self) -> None:
        await self.link.now_s()

    async def _status_tick(self) -> None:
        assert self.publishing.publisher is not None
        if self.publishing.state == "starting" and self.link.connected.is_set():
            self.publishing.state = "running"
        await self.publishing.publisher.send(self.publishing.status_msg())

    # ------------------------------------------------------------------ frames

    async def _process_loop(self) -> None:
        """Process queued frames in order, each in the worker thread."""
        while True:
            await self._handle(await self.acquisition.batches.get())

    async def _handle(self, batch: FrameBatch) -> None:
        """One frame through the worker: measure, model, store; then publish.

        A step that fails ends neither the frame loop nor the daemon: a run
        store that cannot write holds the frame (:class:`HeldWrites`); a frame
        whose processing fails is reported (log, status ``frame_error``),
        counted and skipped, and the next frame takes a new reference.
        """
        pub = self.publishing
        seq, epoch, paused = pub.frames_seen, self.link.epoch, pub.paused
        pub.frames_seen += 1
        writer = self._writer
        assert writer is not None
        hold = batch.hold or ("paused" if paused else None)

        def process() -> FrameOutcome:
            # The curve starts from "now" as the worker takes the frame up, not
            # as it was queued: behind a model change it may wait, and each
            # wall second is many seconds of drift for an accelerated simulator.
            t_now = self.link.clock.at(time.time())
            self.pipeline.push(batch.channels, batch.events)
            outcome = self.pipeline.process(
                batch.frame,
                seq=seq,
                epoch=epoch,
                detected_wall_s=batch.detected_wall_s,
                t_now_s=t_now,
                hold=hold,
            )
            writer.record(outcome)
            return outcome

        try:
            outcome = await self._in_worker(process)
        except Exception as err:
            self._frame_failed(seq, batch, err)
            return
        finally:
            self._store_state()
        self.flags.discard("frame_error")
        pub.faults.frame_problem = None
        self.frames_processed += 1
        self._frame_done.set()
        self.diagnosis.frame_done(self.frames_processed)
        self.closed_loop.frame_done(outcome.record)
        self.link.see_frame_end(outcome.record.t_end_s)
        try:
            self.latencies_s.append(await pub.frame_done(outcome, batch.detected_wall_s))
        except Exception as err:
            self._log_once("publish", f"frame {seq}: not published ({err!r})", err)

    def _frame_failed(self, seq: int, batch: FrameBatch, err: Exception) -> None:
        """A frame's processing raised: say so (once per kind of failure, with
        its traceback), count it, and start a new reference with the next frame."""
        problem = f"frame {seq} (instrument frame {batch.frame.index}): processing failed ({err!r})"
        self._log_once(f"frame:{type(err).__name__}:{err}", problem, err)
        faults = self.publishing.faults
        # Nothing of it is stored: its number goes to the next frame.
        self.publishing.frames_seen -= 1
        faults.frames_failed += 1
        faults.frame_problem = problem
        self.flags.add("frame_error")
        # What the failure left half-done is not trusted: a new reference.
        self.pipeline.request_reset()
        self.link.see_frame_end(batch.frame.t_end_s)

    def _log_once(self, key: str, message: str, err: BaseException) -> None:
        if key in self._failures_logged:
            log.error("%s", message)
            return
        self._failures_logged.add(key)
        log.error("%s; the daemon goes on", message, exc_info=err)

    def _store_state(self) -> None:
        """The writer's state into the status (flag ``store_error`` and counts)."""
        w = self._writer
        if w is None:
            return
        faults = self.publishing.faults
        faults.store_problem = w.problem
        faults.frames_held = w.held
        faults.frames_unstored = w.frames_dropped
        if w.problem is None:
            self.flags.discard("store_error")
        else:
            self.flags.add("store_error")

    async def _store_retry(self) -> None:
        """While frames are held, try to write them even if no frame comes."""
        w = self._writer
        if w is None or w.problem is None:
            return
        await self._in_worker(w.flush)
        self._store_state()

    def _close_store(self) -> None:
        """Write what is held one last time, then close the store."""
        w, store = self._writer, self._store
        if store is None:
            return
        if w is not None and w.problem is not None and not w.flush():
            log.error(
                "run store %s: %d measured frame(s) could not be stored before the daemon "
                "stopped (%s); what was stored before is intact",
                store.path, w.held, w.problem,
            )  # fmt: skip
        try:
            store.close()
        except Exception as err:
            log.error("run store %s: not closed cleanly (%s)", store.path, err)

    async def wait_for_frames(self, n: int) -> None:
        """Return once this run has processed at least ``n`` frames (bound it with a timeout)."""
        while self.frames_processed < n:
            self._frame_done.clear()
            await self._frame_done.wait()

    async def wait_for_flag(self, flag: str, *, poll_s: float = 0.02) -> None:
        """Return once status flag ``flag`` is raised (bound it with a timeout)."""
        for _ in itertools.count():
            if flag in self.flags:
                return
            await asyncio.sleep(poll_s)

    async def _publish_diagnosis(self, msg: DiagnosisMsg) -> None:
        if self.publishing.publisher is not None:
            await self.publishing.publisher.send(msg)

    async def _serve_control(self) -> None:
        assert self._control is not None
        await self.controller.serve(self._control)


def _stored_instrument(meta: dict[str, str]) -> InstrumentInfo | None:
    """The instrument a run store was recorded with (its ``instrument_*`` meta)."""
    names = [f.name for f in dataclasses.fields(InstrumentInfo)]
    if not all(f"instrument_{n}" in meta for n in names):
        return None
    return InstrumentInfo(**{n: meta[f"instrument_{n}"] for n in names})


async def _supervised(name: str, fn: Callable[[], Awaitable[None]]) -> None:
    """Run one loop; a loop that dies logs why, and the task group re-raises."""
    try:
        await fn()
    except asyncio.CancelledError:
        raise
    except BaseException:
        log.exception("service task %r died", name)
        raise

"""The drift daemon: an asyncio service around :class:`FramePipeline`.

Tasks (one :class:`asyncio.TaskGroup`; any task that dies logs why and the
group re-raises, cancelling the others):

``connect``   connects the instrument, and reconnects after a failure
``clock``     reads the instrument clock (for the offset stream and staleness)
``frames``    polls for a new frame, reads the event log up to it, queues it
``process``   runs the pipeline on queued frames in the worker thread, publishes
``channels``  polls temperature/humidity into the model history
``events``    polls the event log (offset moves, tip changes, ...)
``offset``    publishes d(t) at ``offset_rate_hz`` (never waits for a frame)
``status``    heartbeat
``control``   answers the control socket
``closed``    (closed loop only) applies the offset on the instrument

Instrument failures (typed driver errors, OS errors, timeouts) do not stop
the daemon: the ``instrument_error`` flag is raised, the connection is closed
and reopened after ``reconnect_delay_s``. An instrument whose clock went
backwards after a reconnect was restarted: the service starts a new *epoch*,
shifts the instrument's times so the service's time axis stays increasing,
re-reads its event log from the start and takes a new registration reference.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import functools
import itertools
import logging
import math
import statistics
import time
from collections import deque
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, Literal, TypeVar

import zmq.asyncio

from afmdrift.config import AfmdriftConfig, load_config
from afmdrift.drivers import Instrument
from afmdrift.errors import AfmdriftError
from afmdrift.model import OffsetCurve, commanded_offset_nm, make_predictor
from afmdrift.pipeline import FrameOutcome, FramePipeline
from afmdrift.records import ChannelSample, Event, Frame, LoggedEvent
from afmdrift.registration import warm_up
from afmdrift.service._record import process_and_record
from afmdrift.service._safety import InstrumentClock, OffsetLimiter, is_stale
from afmdrift.service._store import RunStore
from afmdrift.service._zmq import ControlSocket, CurveKeys, Publisher, load_curve_keys
from afmdrift.wire import (
    ClockSync,
    ControlReply,
    ControlRequest,
    FrameMsg,
    ModelMsg,
    OffsetMsg,
    StatusMsg,
)

__all__ = ["INSTRUMENT_ERRORS", "DriftService"]

log = logging.getLogger(__name__)

#: Errors that mean "the instrument or its connection failed", not a bug.
INSTRUMENT_ERRORS: tuple[type[BaseException], ...] = (
    AfmdriftError,
    OSError,
    TimeoutError,
    EOFError,
)

_T = TypeVar("_T")

#: Frames waiting for the worker before the oldest is dropped (and logged).
_FRAME_QUEUE = 32

#: Consecutive failed calls (garbled replies, timeouts) before a reconnect.
_FAILURES_BEFORE_RECONNECT = 3


class _InstrumentDownError(Exception):
    """Internal: an instrument call failed; the reconnect task takes over."""


class DriftService:
    """The drift daemon.

    Parameters
    ----------
    config : AfmdriftConfig
        Full configuration (``service``, ``registration``, ``model``).
    instrument : Instrument
        An unconnected instrument (driver, simulator client or replay).
    ctx : zmq.asyncio.Context, optional
        Context for the sockets (default: the process-wide instance).
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
        self.instrument = instrument
        self.ctx = ctx
        self.config_path = Path(config_path) if config_path is not None else None
        self.pipeline = pipeline or FramePipeline(config=config)
        self.ready = asyncio.Event()
        self.pub_endpoint = ""
        self.control_endpoint = ""
        self.clock = InstrumentClock()
        self.limiter = OffsetLimiter(
            max_offset_nm=self.svc.max_offset_nm, max_rate_nm_s=self.svc.max_offset_rate_nm_s
        )
        self.frames_processed = 0
        self.latencies_s: deque[float] = deque(maxlen=1000)
        self.state = "starting"
        self.flags: set[str] = {"no_model"}
        self.paused = False
        self.curve: OffsetCurve | None = None
        self._seq = 0
        self._epoch = 0
        self._t_offset_s = 0.0
        self._pub_seq = {"offset": 0, "model": 0, "frame": 0, "status": 0}
        self._last_frame_key: tuple[int, float] | None = None
        self._last_frame_t_s: float | None = None
        self._frame_ends: deque[float] = deque(maxlen=16)
        self._errors_nm: deque[float] = deque(maxlen=self.svc.rolling_window)
        self._last_service_t_s: float | None = None
        self._event_cursor = 0
        self._events: list[Event] = []
        self._pending_channels: list[ChannelSample] = []
        self._pending_events: list[LoggedEvent] = []
        self._event_lock = asyncio.Lock()
        self._connected = asyncio.Event()
        self._reconnect = asyncio.Event()
        self._absolute_offset_base: tuple[float, float] | None = None
        self._last_command: tuple[float, float] | None = None
        self._resumed = False
        self._store: RunStore | None = None
        self._publisher: Publisher | None = None
        self._control: ControlSocket | None = None
        self._curve_keys: CurveKeys | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._last_offset: OffsetMsg | None = None
        self._frame_done = asyncio.Event()
        self._frames: asyncio.Queue[tuple[Frame, float]] = asyncio.Queue(maxsize=_FRAME_QUEUE)
        self.frames_dropped = 0
        self._consecutive_failures = 0
        self.instrument_errors = 0

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        """Run until cancelled; sockets, store, worker and instrument are closed on exit."""
        own_ctx = self.ctx is None
        ctx = self.ctx or zmq.asyncio.Context()
        try:
            self._curve_keys = load_curve_keys(self.svc)
            if self._curve_keys is not None:
                self._curve_keys.start(ctx)
            self._store = RunStore(
                self.svc.run_dir,
                archive_frames=self.svc.archive_frames,
                keep_model_states=self.svc.keep_model_states,
                check_same_thread=False,
            )
            self._executor = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="afmdrift-worker"
            )
            # Compile (or load from Numba's cache) the registration kernels
            # now: on the first frame it would hold the GIL for 0.5 s (10 s
            # after an install) and stall the offset stream mid-run.
            warm_s = await asyncio.get_running_loop().run_in_executor(
                self._executor, functools.partial(warm_up, self.config.registration)
            )
            log.info("registration kernels ready in %.2f s", warm_s)
            await self._resume_from_store()
            self._publisher = Publisher(
                self.svc.pub_endpoint, ctx=ctx, sndhwm=self.svc.sndhwm, curve=self._curve_keys
            )
            self._control = ControlSocket(
                self.svc.control_endpoint, ctx=ctx, curve=self._curve_keys
            )
            self.pub_endpoint = self._publisher.endpoint
            self.control_endpoint = self._control.endpoint
            log.info(
                "drift service: publishing on %s, control on %s, run store %s",
                self.pub_endpoint,
                self.control_endpoint,
                self._store.path,
            )
            self.ready.set()
            self._reconnect.set()
            async with asyncio.TaskGroup() as tg:
                loops: dict[str, Callable[[], Awaitable[None]]] = {
                    "connect": self._connect_loop,
                    "clock": self._clock_loop,
                    "frames": self._frame_loop,
                    "process": self._process_loop,
                    "channels": self._channel_loop,
                    "events": self._event_loop,
                    "offset": self._offset_loop,
                    "status": self._status_loop,
                    "control": self._control_loop,
                }
                if self.svc.closed_loop:
                    loops["closed"] = self._closed_loop
                for name, fn in loops.items():
                    tg.create_task(self._supervised(name, fn), name=f"afmdrift-{name}")
        finally:
            self.state = "stopping"
            await self._shutdown(ctx if own_ctx else None)

    async def _shutdown(self, own_ctx: zmq.asyncio.Context | None) -> None:
        if self._executor is not None:
            # Let a frame in flight finish writing: the store stays consistent.
            await asyncio.shield(asyncio.to_thread(self._executor.shutdown, wait=True))
        try:
            await self.instrument.close()
        except INSTRUMENT_ERRORS as err:
            log.warning("closing the instrument failed: %s", err)
        if self._store is not None:
            self._store.close()
        for sock in (self._publisher, self._control):
            if sock is not None:
                sock.close()
        if self._curve_keys is not None:
            self._curve_keys.stop()
        if own_ctx is not None:
            own_ctx.term()
        log.info("drift service stopped after %d frames", self.frames_processed)

    @staticmethod
    async def _supervised(name: str, fn: Callable[[], Awaitable[None]]) -> None:
        try:
            await fn()
        except asyncio.CancelledError:
            raise
        except BaseException:
            log.exception("service task %r died", name)
            raise

    async def _resume_from_store(self) -> None:
        assert self._store is not None
        assert self._executor is not None
        store = self._store
        state = store.resume_state()
        if state is None:
            return
        records = store.last_frames(max(self.svc.training_window, 1) * 2)
        logged = store.events()
        events = [e for _, _, e in logged]
        channels = store.channels()
        meta = store.meta()
        self._t_offset_s = float(meta.get("t_offset_s", "0"))
        await asyncio.get_running_loop().run_in_executor(
            self._executor,
            lambda: self.pipeline.resume(state, records=records, channels=channels, events=logged),
        )
        self._seq = state.last.seq + 1
        self._epoch = state.epoch
        self._event_cursor = state.event_cursor
        self._events = events
        self._last_frame_key = (
            state.last.instrument_frame,
            state.last.t_end_s - self._t_offset_s,
        )
        self._last_frame_t_s = state.last.t_end_s
        self._frame_ends.extend(r.t_end_s for r in records[-16:])
        self._last_service_t_s = state.last.t_end_s
        self.frames_processed = 0
        for r in records[-self.svc.rolling_window :]:
            if math.isfinite(r.pred_error_nm):
                self._errors_nm.append(r.pred_error_nm)
        self.curve = self.pipeline.curve
        if self.curve is not None:
            self.flags.discard("no_model")
        self._resumed = True
        log.info(
            "resumed run store %s after frame %d (epoch %d)",
            store.path,
            state.last.seq,
            state.epoch,
        )

    # ------------------------------------------------------------------ instrument access

    async def _call(self, fn: Callable[..., Awaitable[_T]], *args: Any) -> _T:
        await self._connected.wait()
        try:
            result = await fn(*args)
        except INSTRUMENT_ERRORS as err:
            self._instrument_failed(fn, err)
            raise _InstrumentDownError from err
        if self._consecutive_failures:
            self._consecutive_failures = 0
            self.flags.discard("instrument_error")
        return result

    def _instrument_failed(self, fn: Callable[..., Any], err: BaseException) -> None:
        """A failed call: a lost connection, or repeated errors, trigger a reconnect.

        A single garbled reply or timeout (the driver has already resynchronised
        the line) only skips this poll.
        """
        self._consecutive_failures += 1
        self.instrument_errors += 1
        self.flags.add("instrument_error")
        lost = isinstance(err, ConnectionError | EOFError) or (
            isinstance(err, OSError) and not isinstance(err, TimeoutError)
        )
        if not lost and self._consecutive_failures < _FAILURES_BEFORE_RECONNECT:
            log.warning(
                "instrument call %s failed: %s: %s",
                getattr(fn, "__name__", fn),
                type(err).__name__,
                err,
            )
            return
        if self._connected.is_set():
            log.warning(
                "instrument call %s failed: %s: %s; reconnecting",
                getattr(fn, "__name__", fn),
                type(err).__name__,
                err,
            )
        self._connected.clear()
        self._reconnect.set()

    async def _connect_loop(self) -> None:
        first = True
        while True:
            await self._reconnect.wait()
            self._reconnect.clear()
            while True:
                if not first:
                    try:
                        await self.instrument.close()
                    except INSTRUMENT_ERRORS as err:
                        log.debug("close before reconnect: %s", err)
                    await asyncio.sleep(self.svc.reconnect_delay_s)
                first = False
                try:
                    await self.instrument.connect()
                    info = await self.instrument.identify()
                    now = await self.instrument.now_s()
                    offset = await self.instrument.get_offset()
                except INSTRUMENT_ERRORS as err:
                    log.warning("instrument connection failed: %s: %s", type(err).__name__, err)
                    self.flags.add("instrument_error")
                    continue
                break
            self._on_connected(now, offset)
            log.info(
                "connected to %s %s (serial %s, firmware %s) at t=%.3f s",
                info.vendor,
                info.model,
                info.serial,
                info.firmware,
                now,
            )
            if self._store is not None:
                ident = {f"instrument_{k}": str(v) for k, v in dataclasses.asdict(info).items()}
                await self._in_worker(functools.partial(self._store.set_meta, ident))
            self.flags.discard("instrument_error")
            self._consecutive_failures = 0
            self._connected.set()

    def _on_connected(self, now_s: float, offset: tuple[float, float]) -> None:
        t = self._observe_now(now_s)
        if self._last_frame_t_s is None and self.svc.expected_frame_interval_s is not None:
            self._last_frame_t_s = t  # staleness counts from the first connection
        moved = commanded_offset_nm([t], self._events)[0]
        self._absolute_offset_base = (offset[0] - moved[0], offset[1] - moved[1])

    def _observe_now(self, now_s: float) -> float:
        """Record an instrument clock reading; a clock that went back starts an epoch.

        Returns the reading on the service's time axis.
        """
        if self._last_service_t_s is not None and now_s + self._t_offset_s < (
            self._last_service_t_s - 1e-6
        ):
            self._new_epoch(now_s)
        t = now_s + self._t_offset_s
        self.clock.observe(wall_s=time.time(), instrument_s=t)
        self._last_service_t_s = t
        return t

    def _new_epoch(self, now_s: float) -> None:
        assert self._last_service_t_s is not None
        self._epoch += 1
        # The restarted instrument's time 0 is placed right after the last time
        # seen, so everything it logged since its start (frames, events,
        # channels) falls after the previous epoch; the outage is not counted.
        last_seen = max(self._last_service_t_s, self._last_frame_t_s or -math.inf)
        self._t_offset_s = last_seen
        self._event_cursor = 0
        self._last_frame_key = None
        self.pipeline.request_reset()
        log.warning(
            "instrument clock went back to %.3f s: it was restarted; epoch %d, "
            "times shifted by %.3f s, new registration reference",
            now_s,
            self._epoch,
            self._t_offset_s,
        )
        if self._store is not None and self._executor is not None:
            self._executor.submit(self._store.set_meta, {"t_offset_s": repr(self._t_offset_s)})

    def _shift(self, t_s: float) -> float:
        return t_s + self._t_offset_s

    # ------------------------------------------------------------------ loops

    async def _every(
        self,
        period_s: float,
        body: Callable[[], Awaitable[None]],
        *,
        catch_up_s: float = 0.0,
    ) -> None:
        """Run ``body`` every ``period_s`` on an absolute schedule.

        A tick that comes late by up to ``catch_up_s`` is followed by the
        missed ones at once, so the average rate holds (the offset stream: the
        event loop's sleeps are rounded up to whole milliseconds, which alone
        would turn 1 kHz into about 700 Hz). Later than that, the schedule
        restarts from now rather than bursting (polls after a reconnect).
        """
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            next_t += period_s
            delay = next_t - loop.time()
            await asyncio.sleep(delay if delay > 0 else 0.0)
            if loop.time() - next_t > max(period_s, catch_up_s):
                next_t = loop.time()
            try:
                await body()
            except _InstrumentDownError:
                continue

    async def _clock_loop(self) -> None:
        async def tick() -> None:
            self._observe_now(await self._call(self.instrument.now_s))

        await self._every(self.svc.clock_sync_interval_s, tick)

    async def _channel_loop(self) -> None:
        async def tick() -> None:
            sample = await self._call(self.instrument.read_channels)
            self._pending_channels.append(
                ChannelSample(t_s=self._shift(sample.t_s), values=dict(sample.values))
            )

        await self._every(self.svc.channel_poll_interval_s, tick)

    async def _event_loop(self) -> None:
        await self._every(self.svc.event_poll_interval_s, self._poll_events)

    async def _poll_events(self) -> None:
        async with self._event_lock:
            start = self._event_cursor
            entries = await self._call(self.instrument.events, start)
            for k, e in enumerate(entries):
                shifted = dataclasses.replace(e, t_s=self._shift(e.t_s))
                self._pending_events.append(LoggedEvent(self._epoch, start + k, shifted))
                self._events.append(shifted)
            self._event_cursor = start + len(entries)

    async def _frame_loop(self) -> None:
        async def tick() -> None:
            frame = await self._call(self.instrument.latest_frame)
            if frame is None:
                return
            key = (frame.index, frame.t_end_s)
            if key == self._last_frame_key:
                return
            if self._last_frame_key is not None and frame.t_end_s < self._last_frame_key[1]:
                # An older frame than the last one: the instrument was restarted
                # (its driver may have reconnected on its own). Read its clock.
                epoch = self._epoch
                self._observe_now(await self._call(self.instrument.now_s))
                if epoch == self._epoch:
                    log.warning("frame %d ends before the previous one; ignored", frame.index)
                    return
            detected = time.time()
            if self._last_frame_key is not None and frame.index > self._last_frame_key[0] + 1:
                log.warning(
                    "instrument frames %d..%d were replaced before they were read",
                    self._last_frame_key[0] + 1,
                    frame.index - 1,
                )
            await self._poll_events()  # every offset move up to this frame is known
            self._last_frame_key = key
            shifted = dataclasses.replace(
                frame,
                t_start_s=self._shift(frame.t_start_s),
                t_end_s=self._shift(frame.t_end_s),
            )
            if self._frames.full():
                dropped, _ = self._frames.get_nowait()
                self.frames_dropped += 1
                log.warning(
                    "processing is %d frames behind; frame %d dropped",
                    self._frames.qsize() + 1,
                    dropped.index,
                )
            # The event-log entries read so far belong with this frame.
            self._frames.put_nowait((shifted, detected))

        await self._every(self.svc.frame_poll_interval_s, tick)

    async def _process_loop(self) -> None:
        """Process queued frames in order; polling goes on meanwhile, so a frame that
        takes longer than the frame period does not make the next one be missed."""
        while True:
            frame, detected = await self._frames.get()
            await self._handle_frame(frame, detected)

    async def _in_worker(self, fn: Callable[[], _T]) -> _T:
        assert self._executor is not None
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn)

    async def _handle_frame(self, frame: Frame, detected_wall_s: float) -> None:
        channels, self._pending_channels = self._pending_channels, []
        events, self._pending_events = self._pending_events, []
        seq, epoch, paused = self._seq, self._epoch, self.paused
        self._seq += 1
        assert self._store is not None
        store = self._store
        outcome = await self._in_worker(
            lambda: process_and_record(
                self.pipeline,
                store,
                frame,
                channels=channels,
                events=events,
                seq=seq,
                epoch=epoch,
                detected_wall_s=detected_wall_s,
                paused=paused,
                t_now_s=self.clock.at(time.time()),
            )
        )
        await self._after_frame(outcome, detected_wall_s)

    async def _after_frame(self, outcome: FrameOutcome, detected_wall_s: float) -> None:
        r = outcome.record
        self.frames_processed += 1
        self._frame_done.set()
        self._frame_ends.append(r.t_end_s)
        self._last_frame_t_s = r.t_end_s
        if outcome.low_confidence:
            self.flags.add("low_confidence")
        elif r.fed_model:
            self.flags.discard("low_confidence")
        if math.isfinite(r.pred_error_nm):
            self._errors_nm.append(r.pred_error_nm)
        if outcome.curve is not None:
            if self.curve is None and not self._resumed and math.isfinite(r.t_mid_s):
                t_now = self.clock.at(time.time())
                self.limiter.hold(t_now if t_now is not None else r.t_end_s, 0.0, 0.0)
            self.curve = outcome.curve
            self.flags.discard("no_model")
        assert self._publisher is not None
        now = time.time()
        if outcome.curve_dict is not None and r.fed_model:
            anchor = self.clock.anchor()
            wall, inst, rate = anchor if anchor is not None else (now, r.t_end_s, 1.0)
            await self._publisher.send(
                ModelMsg(
                    seq=self._next("model"),
                    frame=r.seq,
                    t_s=r.t_mid_s,
                    wall_s=now,
                    predictor=outcome.predictor_name,
                    curve=outcome.curve_dict,
                    clock=ClockSync(wall_s=wall, instrument_s=inst, rate=rate),
                    max_offset_nm=self.svc.max_offset_nm,
                    max_offset_rate_nm_s=self.svc.max_offset_rate_nm_s,
                )
            )
        latency = time.time() - detected_wall_s
        self.latencies_s.append(latency)
        await self._publisher.send(
            FrameMsg(
                seq=self._next("frame"),
                frame=r.seq,
                instrument_frame=r.instrument_frame,
                t_s=r.t_mid_s,
                wall_s=now,
                dx_nm=_opt(r.dx_nm),
                dy_nm=_opt(r.dy_nm),
                x_nm=_opt(r.x_nm),
                y_nm=_opt(r.y_nm),
                sigma_nm=_opt(r.sigma_nm),
                valid=r.valid,
                fed_model=r.fed_model,
                reason=r.reason,
                valid_blocks=r.valid_blocks,
                total_blocks=r.total_blocks,
                field=outcome.field,
                pred_x_nm=_opt(r.pred_x_nm),
                pred_y_nm=_opt(r.pred_y_nm),
                pred_error_nm=_opt(r.pred_error_nm),
                latency_s=latency,
            )
        )

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

    def _next(self, topic: str) -> int:
        n = self._pub_seq[topic]
        self._pub_seq[topic] = n + 1
        return n

    def expected_interval_s(self) -> float | None:
        """Configured frame interval, else the median of recent ones (instrument s)."""
        if self.svc.expected_frame_interval_s is not None:
            return self.svc.expected_frame_interval_s
        if len(self._frame_ends) < 2:
            return None
        ends = list(self._frame_ends)
        diffs = [b - a for a, b in itertools.pairwise(ends) if b > a]
        return statistics.median(diffs) if diffs else None

    def stale(self, now_s: float | None) -> bool:
        if now_s is None:
            return False
        return is_stale(
            now_s=now_s,
            last_frame_t_s=self._last_frame_t_s,
            expected_interval_s=self.expected_interval_s(),
            factor=self.svc.stale_factor,
        )

    async def _offset_loop(self) -> None:
        assert self._publisher is not None
        publisher = self._publisher

        async def tick() -> None:
            wall = time.time()
            t = self.clock.at(wall)
            msg = self._offset_sample(wall, t)
            self._last_offset = msg
            await publisher.send(msg)

        await self._every(1.0 / self.svc.offset_rate_hz, tick, catch_up_s=0.05)

    @property
    def last_offset(self) -> OffsetMsg | None:
        """The offset sample published last (``None`` before the first)."""
        return self._last_offset

    def _offset_sample(self, wall_s: float, t_s: float | None) -> OffsetMsg:
        """The next offset sample: d(t_s) through the limiter, with its flags.

        Advances the limiter and the sequence number: only the offset loop calls it.
        """
        seq = self._next("offset")
        if t_s is None or self.curve is None:
            return OffsetMsg(
                seq=seq, t_s=t_s or 0.0, wall_s=wall_s, x_nm=0.0, y_nm=0.0, valid=False
            )
        target = self.curve.at([t_s])
        tx, ty = float(target.reshape(-1)[0]), float(target.reshape(-1)[1])
        if self._resumed and self.limiter.last is None:
            self.limiter.hold(t_s, tx, ty)  # continue from the resumed model, no ramp
        out = self.limiter.apply(t_s, tx, ty)
        if out.clamped:
            self.flags.add("clamped")
        else:
            self.flags.discard("clamped")
        stale = self.stale(t_s)
        if stale:
            self.flags.add("stale")
        else:
            self.flags.discard("stale")
        valid = not (stale or self.paused or "instrument_error" in self.flags)
        return OffsetMsg(
            seq=seq,
            t_s=t_s,
            wall_s=wall_s,
            x_nm=out.x_nm,
            y_nm=out.y_nm,
            valid=valid,
            clamped=out.clamped,
        )

    def status_msg(self) -> StatusMsg:
        wall = time.time()
        t = self.clock.at(wall)
        flags = set(self.flags)
        if self.paused:
            flags.add("paused")
        if self.stale(t):
            flags.add("stale")
        state: Literal["starting", "running", "paused", "stale", "stopping"]
        if self.state == "stopping":
            state = "stopping"
        elif self.paused:
            state = "paused"
        elif self.state == "starting":
            state = "starting"
        elif "stale" in flags:
            state = "stale"
        else:
            state = "running"
        errs = list(self._errors_nm)
        return StatusMsg(
            seq=self._next("status"),
            t_s=t,
            wall_s=wall,
            state=state,
            flags=sorted(flags),
            frames=self._seq,
            last_frame_t_s=self._last_frame_t_s,
            expected_frame_interval_s=self.expected_interval_s(),
            rolling_error_nm=statistics.fmean(errs) if errs else None,
            rolling_max_error_nm=max(errs) if errs else None,
            rolling_window=self.svc.rolling_window,
        )

    async def _status_loop(self) -> None:
        assert self._publisher is not None
        publisher = self._publisher

        async def tick() -> None:
            if self.state == "starting" and self._connected.is_set():
                self.state = "running"
            await publisher.send(self.status_msg())

        await self._every(self.svc.heartbeat_interval_s, tick)

    async def _control_loop(self) -> None:
        assert self._control is not None
        control = self._control
        while True:
            req = await control.receive()
            if isinstance(req, ControlReply):
                await control.reply(req)
                continue
            try:
                reply = await self._handle_control(req)
            except AfmdriftError as err:
                reply = ControlReply(ok=False, error=str(err))
            await control.reply(reply)

    async def _handle_control(self, req: ControlRequest) -> ControlReply:
        log.info("control: %s", req.cmd)
        if req.cmd == "pause":
            self.paused = True
        elif req.cmd == "resume":
            self.paused = False
        elif req.cmd == "reset_reference":
            self.pipeline.request_reset()
        elif req.cmd == "reload_model":
            await self._reload_model(req.config_path)
        return ControlReply(ok=True, status=self.status_msg())

    async def _reload_model(self, config_path: str | None) -> None:
        path = config_path or (str(self.config_path) if self.config_path else None)
        if path is None:
            raise AfmdriftError(
                "reload_model: the daemon was started without a configuration file; "
                "name one in config_path"
            )
        new = load_config(path)

        def reload() -> int:
            predictor = make_predictor(new.model.predictor, new.model)
            return self.pipeline.reload_model(predictor)

        n = await self._in_worker(reload)
        self.config = self.config.model_copy(update={"model": new.model})
        self.pipeline.config = self.config
        if self.pipeline.curve is not None:
            self.curve = self.pipeline.curve
        log.info(
            "reloaded [model] from %s (%s), refitted on %d points", path, new.model.predictor, n
        )

    async def _closed_loop(self) -> None:
        async def tick() -> None:
            last = self._last_offset
            base = self._absolute_offset_base
            if last is None or not last.valid or base is None or self.curve is None:
                return
            t_ref = self.pipeline.t_ref_s
            if t_ref is None:
                return
            moved_ref = commanded_offset_nm([t_ref], self._events)[0]
            x = base[0] + moved_ref[0] + last.x_nm
            y = base[1] + moved_ref[1] + last.y_nm
            if (
                self._last_command is not None
                and math.hypot(x - self._last_command[0], y - self._last_command[1])
                < self.svc.closed_loop_min_step_nm
            ):
                return
            await self._call(self.instrument.set_offset, x, y)
            self._last_command = (x, y)

        await self._every(self.svc.closed_loop_interval_s, tick)


def _opt(v: float) -> float | None:
    return v if math.isfinite(v) else None

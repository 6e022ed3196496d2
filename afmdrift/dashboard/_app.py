"""The dashboard server: follows a daemon and its run store, serves a live page.

One asyncio task set: the ZeroMQ follower (every published message), the
store poller (new rows of the read-only run store every ``store_poll_s``),
the ticker (offset envelope, channels, events and the service summary to the
pages every ``tick_s``), and the frame-view worker (re-measures the latest
archived frame in a thread). Pages connect with a WebSocket, receive a
snapshot, then the same deltas as every other page: a delta is serialised
once and queued to each page, and a page whose queue is full is disconnected
(it reconnects and starts again from a snapshot) so one slow browser never
holds the others back or grows memory.

The HTTP side is aiohttp; the page, its script and Plotly's JavaScript (from
the ``plotly`` package) are served from this process, so the page needs no
network beyond the dashboard's own address.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import math
import secrets
import socket
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import zmq
import zmq.asyncio
from aiohttp import WSMsgType, web

from afmdrift.client import ClientError, control
from afmdrift.config import AfmdriftConfig, check_endpoint, host_is_loopback
from afmdrift.dashboard._live import LiveDiagnoses, live_finding
from afmdrift.dashboard._sources import DiagnosisFile, FrameImages, frame_view
from afmdrift.dashboard._state import RunState, TruthSource
from afmdrift.dashboard._store import DB_FILE, DashboardError, RunReader, StoreNotReadyError
from afmdrift.errors import AfmdriftError, InputError
from afmdrift.model import OffsetCurve, resolve_terms
from afmdrift.service import OffsetLimiter
from afmdrift.wire import (
    DiagnosisMsg,
    FrameMsg,
    ModelMsg,
    OffsetMsg,
    StatusMsg,
    WireError,
    decode,
)

__all__ = ["Dashboard"]

log = logging.getLogger(__name__)

#: Messages queued to one page before it is considered too slow and dropped.
_CLIENT_QUEUE = 256
#: Frames searched backwards for the previous accepted frame with an image.
_VIEW_LOOKBACK = 50
_TOKEN_COOKIE = "afmdrift_dashboard_token"
#: Messages taken from the SUB socket in one go before yielding to other tasks.
_DRAIN_MAX = 2000
#: Shortest interval between two reads of the SUB socket, s.
_BATCH_S = 0.01
#: While waiting for a run store, the log repeats that it waits this often, s.
_STORE_WAIT_LOG_S = 60.0
#: Where the page's per-process secret against cross-site requests goes in index.html.
_CSRF_SLOT = b"__AFMDRIFT_CSRF__"
#: Largest body of a control request from the page, bytes.
_MAX_CONTROL_BODY = 4096


def _dumps(doc: Any) -> str:
    return json.dumps(doc, allow_nan=False, separators=(",", ":"))


class _Page:
    """One connected browser: its WebSocket and its bounded send queue."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.queue: asyncio.Queue[str] = asyncio.Queue(maxsize=_CLIENT_QUEUE)
        self.writer: asyncio.Task[None] | None = None

    async def write(self) -> None:
        while True:
            text = await self.queue.get()
            await self.ws.send_str(text)

    async def stop_writing(self) -> None:
        if self.writer is not None:
            self.writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self.writer


class Dashboard:
    """The ``afmdrift dashboard`` server.

    Parameters
    ----------
    run_dir : path-like, optional
        Run directory to read (read-only). Without ``pub_endpoint`` the run is
        shown as finished: nothing is live.
    pub_endpoint : str, optional
        The daemon's PUB endpoint to follow (``service.pub_endpoint``).
    config : AfmdriftConfig, optional
        Registration parameters for the frame view (a replay's stored
        configuration takes precedence) and the default rolling window.
    host, port : str, int
        Address to serve on; port 0 picks a free port (see :attr:`url`).
    token : str, optional
        Access token; required when ``host`` is not a loopback address. Pages
        pass it once as ``?token=...`` and then hold it in a cookie.
    control_endpoint : str, optional
        The daemon's control socket (``service.control_endpoint``): with
        ``control_token``, the page's "Add to model" sends ``add_term`` there.
    control_token : str, optional
        The daemon's control token (its ``control.token``); it must also be
        the access ``token``, so only a page opened with it can change the
        model. Without it the button is shown disabled with the reason.
    truth : TruthSource, optional
        The true drift (a session's ``truth.csv``, an in-process simulator).
    session : Session, optional
        The session a replayed run came from (frame images for the frame view).
    diagnosis_path : path-like, optional
        A diagnose JSON result (default ``RUN_DIR/diagnosis.json``).
    ctx : zmq.asyncio.Context, optional
        Context for the subscriber (default: a private one, terminated on close).
    max_frames : int
        Frames held in memory and on the page (the newest).
    store_poll_s, tick_s : float
        Store polling and page update periods, s.
    wait_for_store : bool
        Live mode (with ``pub_endpoint``): when the run directory, its
        ``run.sqlite`` or the store's tables do not exist yet, wait for them
        (the page and the log say so) and follow the run once they appear,
        instead of failing. The daemon creates them when it starts, so a
        dashboard started first (a service unit, a script) waits for it.
    first_message_timeout_s : float
        Live mode without a run store: fail when the daemon sends nothing this long.
    """

    def __init__(
        self,
        *,
        run_dir: str | Path | None = None,
        pub_endpoint: str | None = None,
        config: AfmdriftConfig | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        token: str | None = None,
        control_endpoint: str | None = None,
        control_token: str | None = None,
        truth: TruthSource | None = None,
        session: Any = None,
        diagnosis_path: str | Path | None = None,
        ctx: zmq.asyncio.Context | None = None,
        max_frames: int = 5000,
        store_poll_s: float = 1.0,
        tick_s: float = 0.25,
        wait_for_store: bool = False,
        first_message_timeout_s: float = 10.0,
    ) -> None:
        if run_dir is None and pub_endpoint is None:
            raise DashboardError("give a run directory, a PUB endpoint, or both")
        if not host_is_loopback(host) and not token:
            raise DashboardError(
                f"serving on {host} (not a loopback address) needs an access token"
            )
        if not 0 <= port <= 65535:
            raise DashboardError(f"port must be between 0 and 65535, got {port}")
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.pub_endpoint = pub_endpoint
        self.config = config or AfmdriftConfig()
        self.host = host
        self.port = port
        self.token = token
        if control_token is not None and control_token != token:
            raise DashboardError(
                "the control token must be the dashboard's access token as well (--token-file "
                "RUN_DIR/control.token): a page without it must not change the model"
            )
        self.control_endpoint = control_endpoint
        self.control_token = control_token
        #: Embedded in the page and required on its POSTs: another site's page
        #: cannot read it, so it cannot forge them (docs/dashboard.md).
        self._csrf = secrets.token_urlsafe(32)
        self.state = RunState(
            max_frames=max_frames,
            rolling_window=self.config.service.rolling_window,
            truth=truth,
            pub_endpoint=pub_endpoint,
        )
        if self.run_dir is not None:
            self.state.store_path = str(self.run_dir / DB_FILE)
        self.images = FrameImages(run_dir=self.run_dir, session=session)
        diag = diagnosis_path or (None if self.run_dir is None else self.run_dir / "diagnosis.json")
        self.diagnosis = None if diag is None else DiagnosisFile(Path(diag))
        if self.diagnosis is None:
            self.state.diagnosis_note = "no run directory, so no diagnose result"
        self.live_diagnoses = None if self.run_dir is None else LiveDiagnoses(self.run_dir)
        self.state.control = self._control_state()
        self._own_ctx = ctx is None
        self._ctx = ctx
        self.store_poll_s = store_poll_s
        self.tick_s = tick_s
        self.wait_for_store = wait_for_store
        self.first_message_timeout_s = first_message_timeout_s
        self.silent_after_s = 3.0 * max(self.config.service.heartbeat_interval_s, 1.0)
        self._reader: RunReader | None = None
        self._store_wait_since: float | None = None
        self._store_wait_logged = 0.0
        self._sub: zmq.asyncio.Socket | None = None
        self._cursors = {"frame": -1, "channel": 0, "event": 0, "model": -1}
        self._registration_config = self.config
        self._pages: set[_Page] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._runner: web.AppRunner | None = None
        self._sent_offset = (-1, 0)
        self._sent_channels: dict[str, tuple[int, int]] = {}
        self._new_events: list[Any] = []
        self._view_wanted = asyncio.Event()
        self._view_seq: int | None = None
        self._plotly_js: bytes | None = None
        self._heard = asyncio.Event()
        self._served_hosts: set[str] = set()
        self.url = ""

    def _control_state(self) -> dict[str, Any]:
        """Whether the page may change the model, and if not, why (shown on the button)."""
        if self.control_token is None:
            return {
                "enabled": False,
                "reason": "this dashboard was started without the daemon's control token: "
                "start it with --token-file RUN_DIR/control.token to add terms from here",
            }
        if self.control_endpoint is None:
            return {
                "enabled": False,
                "reason": "this dashboard does not know the daemon's control socket (--control)",
            }
        return {"enabled": True, "reason": f"add_term on {self.control_endpoint}"}

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> str:
        """Open the store, connect to the daemon, start serving; return the page's URL.

        Raises
        ------
        DashboardError
            Unusable run directory or store, bad endpoint, address in use, or (live,
            without a store) no message from the daemon within the timeout.
        """
        try:
            await self._start()
        except BaseException:
            await self.close()
            raise
        return self.url

    async def _start(self) -> None:
        if self.run_dir is not None:
            try:
                self._open_store()
            except StoreNotReadyError as err:
                if self.pub_endpoint is None or not self.wait_for_store:
                    raise
                self._store_missing(err)
        if self._reader is not None:
            await self._poll_store_once(first=True)
            if self.pub_endpoint is None:
                await asyncio.to_thread(self._offsets_from_stored_curves)
        sub: zmq.asyncio.Socket | None = None
        if self.pub_endpoint is not None:
            try:
                check_endpoint(self.pub_endpoint)
            except ValueError as err:
                raise DashboardError(f"--pub {err} (e.g. tcp://127.0.0.1:5560)") from None
            if self._ctx is None:
                self._ctx = zmq.asyncio.Context()
            sub = self._sub = self._ctx.socket(zmq.SUB)
            sub.setsockopt(zmq.LINGER, 0)
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            try:
                sub.connect(self.pub_endpoint)
            except zmq.ZMQError as err:
                raise DashboardError(f"--pub {self.pub_endpoint}: {err}") from None
        self._plotly_js = _plotly_js()
        await self._serve()
        if sub is not None:
            self._spawn(self._follow(sub), "follow")
        if self.run_dir is not None:
            self._spawn(self._poll_store(), "store")
        self._spawn(self._tick(), "tick")
        self._spawn(self._frame_views(), "frame-view")
        self._want_view()
        if sub is not None and self._reader is None and not self.wait_for_store:
            try:
                await asyncio.wait_for(self._heard.wait(), self.first_message_timeout_s)
            except TimeoutError:
                raise DashboardError(
                    f"no message from {self.pub_endpoint} within "
                    f"{self.first_message_timeout_s:g} s: is afmdrift run publishing there?"
                ) from None

    def _spawn(self, coro: Any, name: str) -> None:
        task = asyncio.create_task(coro, name=f"afmdrift-dashboard-{name}")
        task.add_done_callback(self._task_done)
        self._tasks.append(task)

    @staticmethod
    def _task_done(task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            log.error("dashboard task %s failed", task.get_name(), exc_info=task.exception())

    async def close(self) -> None:
        """Stop every task, close every page, the store and the subscriber."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks.clear()
        if self._sub is not None:
            self._sub.close(linger=0)
            self._sub = None
        for page in list(self._pages):
            with contextlib.suppress(Exception):
                await page.ws.close(code=1001, message=b"dashboard stopping")
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        if self._own_ctx and self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    async def __aenter__(self) -> Dashboard:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def serve_forever(self) -> None:
        """Run until cancelled (SIGINT/SIGTERM in the command line)."""
        await asyncio.Event().wait()

    # ------------------------------------------------------------------ HTTP

    async def _serve(self) -> None:
        app = web.Application(middlewares=[self._auth])
        app.router.add_get("/", self._index)
        app.router.add_get("/dashboard.js", self._static("dashboard.js", "text/javascript"))
        app.router.add_get("/dashboard.css", self._static("dashboard.css", "text/css"))
        app.router.add_get("/plotly.min.js", self._plotly)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/state.json", self._state_json)
        app.router.add_post("/control/add_term", self._add_term)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(64)
        except OSError as err:
            sock.close()
            raise DashboardError(f"cannot serve on {self.host}:{self.port} ({err})") from None
        sock.setblocking(False)
        site = web.SockSite(self._runner, sock)
        await site.start()
        port = sock.getsockname()[1]
        host = f"[{self.host}]" if family == socket.AF_INET6 else self.host
        self._served_hosts = {f"{host}:{port}"}
        if host_is_loopback(self.host):
            self._served_hosts |= {f"{h}:{port}" for h in ("localhost", "127.0.0.1", "[::1]")}
        self.url = f"http://{host}:{port}/" + (f"?token={self.token}" if self.token else "")

    @web.middleware
    async def _auth(self, request: web.Request, handler: Any) -> web.StreamResponse:
        if self.token is None:
            response: web.StreamResponse = await handler(request)
            return response
        given = (
            request.query.get("token")
            or request.cookies.get(_TOKEN_COOKIE)
            or request.headers.get("Authorization", "").removeprefix("Bearer ")
        )
        if not given or not hmac.compare_digest(given.encode(), self.token.encode()):
            return web.Response(status=403, text="afmdrift dashboard: access token required\n")
        response = await handler(request)
        assert isinstance(response, web.StreamResponse)
        if request.query.get("token") and not response.prepared:
            response.set_cookie(_TOKEN_COOKIE, self.token, httponly=True, samesite="Strict")
        return response

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.Response(
            body=_resource("index.html").replace(_CSRF_SLOT, self._csrf.encode("ascii")),
            content_type="text/html",
            headers={"Cache-Control": "no-store"},
        )

    def _static(self, name: str, content_type: str) -> Any:
        body = _resource(name)

        async def handler(request: web.Request) -> web.StreamResponse:
            return web.Response(
                body=body, content_type=content_type, headers={"Cache-Control": "no-cache"}
            )

        return handler

    async def _plotly(self, request: web.Request) -> web.StreamResponse:
        return web.Response(
            body=self._plotly_js,
            content_type="text/javascript",
            headers={"Cache-Control": "max-age=86400"},
        )

    async def _state_json(self, request: web.Request) -> web.StreamResponse:
        """The summary as JSON, for scripts and tests (same as the page's)."""
        return web.Response(
            text=_dumps(
                self.state.summary(now_wall_s=time.time(), silent_after_s=self.silent_after_s)
            ),
            content_type="application/json",
        )

    async def _add_term(self, request: web.Request) -> web.StreamResponse:
        """``POST /control/add_term`` ``{"term": TERM}`` from the page: ``add_term`` to the daemon.

        Refused (nothing sent, nothing changed) with 403 without the control
        token (the access middleware already refused a request without the
        page's token), from another origin, to another host, or without this
        process's page secret (header ``X-Afmdrift-Csrf``); with 400 for a body
        that is not ``{"term": str}`` or a term that does not parse; with 409
        when the daemon refuses it (its reason), 502 when it does not answer.
        """
        if not self.state.control["enabled"]:
            return _refuse(403, self.state.control["reason"])
        origin = request.headers.get("Origin")
        if origin is None or origin != f"{request.scheme}://{request.host}":
            return _refuse(403, f"cross-site request refused (Origin {origin!r})")
        if request.host not in self._served_hosts:
            return _refuse(403, f"request for another host ({request.host!r}) refused")
        given = request.headers.get("X-Afmdrift-Csrf", "")
        if not hmac.compare_digest(given.encode(), self._csrf.encode()):
            return _refuse(403, "the page's secret is missing or wrong (reload the page)")
        if request.content_length is None or request.content_length > _MAX_CONTROL_BODY:
            return _refuse(400, f"a body of at most {_MAX_CONTROL_BODY} bytes is expected")
        try:
            body = json.loads(await request.read())
        except (ValueError, UnicodeDecodeError):
            return _refuse(400, 'the body is not JSON {"term": "..."}')
        term = body.get("term") if isinstance(body, dict) else None
        if not isinstance(term, str) or not term.strip():
            return _refuse(400, 'the body is not {"term": "<a term, docs/model.md>"}')
        plugins = self.config.model.physics.plugins
        try:
            resolve_terms([term.strip()], plugins, key="term")
        except AfmdriftError as err:
            return _refuse(400, str(err))
        assert self.control_endpoint is not None
        try:
            reply = await control(
                self.control_endpoint, "add_term", term=term.strip(),
                token=self.control_token, ctx=self._ctx, timeout_s=10.0,
            )  # fmt: skip
        except WireError as err:
            return _refuse(400, str(err))
        except ClientError as err:
            refused = getattr(err, "reply", None) is not None
            return _refuse(409 if refused else 502, str(err))
        log.info("added the term %r to the daemon's model (from the page)", term.strip())
        terms = None if reply.status is None else getattr(reply.status, "terms", None)
        return web.json_response({"ok": True, "term": term.strip(), "terms": terms})

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            # A page from another site must not read the run through the browser.
            return web.Response(status=403, text="afmdrift dashboard: cross-origin WebSocket\n")
        # Uncompressed: aiohttp compresses a message over 16 KiB (a frame view,
        # a snapshot) in a task of its own that cancelling the page's writer
        # does not stop; when the page has gone, that task fails on the closed
        # connection with no one to see it, and asyncio logs a traceback.
        # Without compression a send is one write into the transport.
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=1 << 16, compress=False)
        await ws.prepare(request)
        page = _Page(ws)
        page.queue.put_nowait(self._snapshot())
        self._pages.add(page)
        page.writer = asyncio.create_task(page.write(), name="afmdrift-dashboard-page")
        try:
            async for msg in ws:
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self._pages.discard(page)
            await page.stop_writing()
        return ws

    def _snapshot(self) -> str:
        return _dumps(
            self.state.snapshot(now_wall_s=time.time(), silent_after_s=self.silent_after_s)
        )

    def _broadcast(self, doc: dict[str, Any]) -> None:
        if not self._pages:
            return
        text = _dumps(doc)
        for page in list(self._pages):
            try:
                page.queue.put_nowait(text)
            except asyncio.QueueFull:
                # Too slow: drop it; the page reconnects and starts from a snapshot.
                self._pages.discard(page)
                log.warning("a dashboard page fell %d messages behind; disconnected", _CLIENT_QUEUE)
                self._tasks.append(asyncio.create_task(self._drop(page)))

    @staticmethod
    async def _drop(page: _Page) -> None:
        # The writer stops first, so the close frame is not interleaved with a message.
        await page.stop_writing()
        await page.ws.close(code=4000, message=b"too slow")

    @property
    def pages(self) -> int:
        """Pages connected now."""
        return len(self._pages)

    # ------------------------------------------------------------------ wire

    async def _follow(self, sub: zmq.asyncio.Socket) -> None:
        # At 1 kHz, one event-loop wake-up per message costs more than the
        # messages themselves: wait until the socket is readable, take
        # everything queued without blocking, then let the next messages
        # gather. The socket is closed by close(), also when this task never ran.
        drain: zmq.Socket[bytes] = zmq.Socket.shadow(sub.underlying)
        while True:
            await sub.poll()  # POLLIN by default
            for _ in range(_DRAIN_MAX):
                try:
                    parts = drain.recv_multipart(flags=zmq.NOBLOCK)
                except zmq.Again:
                    break
                self._handle(parts)
            # At most 100 wake-ups per second: the messages of the next 10 ms
            # queue in the socket (a frame reaches the pages at most 10 ms later).
            await asyncio.sleep(_BATCH_S)

    def _handle(self, parts: list[bytes]) -> None:
        try:
            msg = decode(parts)
        except WireError as err:
            self.state.wire_rejected(str(err))
            return
        self._heard.set()
        if isinstance(msg, OffsetMsg):
            self.state.add_offset(msg)
        elif isinstance(msg, FrameMsg):
            row = self.state.add_frame_msg(msg)
            self._send_frames([row])
            self._want_view()
        elif isinstance(msg, StatusMsg):
            self.state.add_status(msg)
        elif isinstance(msg, ModelMsg):
            self.state.add_model(msg)
        elif isinstance(msg, DiagnosisMsg):
            self.state.add_live_diagnosis(live_finding(msg))

    def _send_frames(self, rows: list[dict[str, Any]]) -> None:
        reset, truth = self.state.take_new_truth()
        self._broadcast({"type": "frames", "rows": rows, "truth": truth, "truth_reset": reset})

    # ------------------------------------------------------------------ store

    @property
    def waiting_for_store(self) -> str | None:
        """What the dashboard is waiting for (the run store and why it is not
        usable yet), or ``None`` when it is not waiting."""
        return self.state.store_note if self.state.store_state == "waiting" else None

    def _store_missing(self, err: StoreNotReadyError) -> None:
        """Live mode, no usable store yet: say what is awaited, on the page and,
        from time to time, in the log."""
        assert self.run_dir is not None
        now = time.monotonic()
        if self._store_wait_since is None:
            self._store_wait_since = self._store_wait_logged = now
            log.info("waiting for the run store %s (%s)", self.run_dir / DB_FILE, err)
        waited = now - self._store_wait_since
        self.state.store_state = "waiting"
        self.state.store_note = (
            f"waiting for {self.run_dir / DB_FILE} ({err}); the run is followed once "
            "afmdrift run creates it"
        )
        if now - self._store_wait_logged >= _STORE_WAIT_LOG_S:
            self._store_wait_logged = now
            log.warning(
                "still waiting for the run store %s after %.0f s (%s): is afmdrift run "
                "writing its run directory there?",
                self.run_dir / DB_FILE,
                waited,
                err,
            )

    def _open_store(self) -> None:
        assert self.run_dir is not None
        reader = RunReader(self.run_dir)
        try:
            self._set_meta(reader.meta())
            ref = reader.session_reference()
        except DashboardError:
            reader.close()
            raise
        self._reader = reader
        if ref is not None:
            self.state.add_records([ref])
        self.state.store_state = "open"
        self.state.store_note = f"{reader.path} (read-only)"
        if self._store_wait_since is not None:
            log.info(
                "run store %s appeared after %.0f s; following it",
                reader.path,
                time.monotonic() - self._store_wait_since,
            )
            self._store_wait_since = None

    def _set_meta(self, meta: dict[str, str]) -> None:
        """The store's ``meta`` table; a replay's stored configuration gives the
        frame view's registration parameters."""
        stored = meta.get("config")
        if stored and stored != self.state.meta.get("config"):
            try:
                self._registration_config = AfmdriftConfig.model_validate_json(stored)
            except ValueError:
                log.warning("%s: stored configuration not readable; using --config", self.run_dir)
        self.state.meta = meta

    async def _poll_store_once(self, *, first: bool = False) -> None:
        reader = self._reader
        assert reader is not None
        c = self._cursors
        rows = await asyncio.to_thread(
            reader.read_since,
            frame_seq=c["frame"],
            channel_id=c["channel"],
            event_id=c["event"],
            model_seq=c["model"],
            max_frames=self.state.max_frames if first else None,
        )
        if rows.frames:
            c["frame"] = rows.frames[-1].seq
            sent = self.state.add_records(rows.frames)
            if not first:
                self._send_frames(sent)
            self._want_view()
        if rows.channels:
            c["channel"] = rows.channels[-1][0]
            self.state.add_channels(rows.channels)
        if rows.events:
            c["event"] = rows.events[-1][0]
            self._new_events.extend(self.state.add_events(rows.events))
        if rows.model is not None:
            c["model"] = rows.model[0]
            self.state.set_model_state(rows.model[1], rows.model[2])
        if rows.meta != self.state.meta:
            self._set_meta(rows.meta)
        changes = await asyncio.to_thread(reader.model_changes)
        if len(changes) != len(self.state.model_changes):
            self.state.set_model_changes(
                [
                    {
                        "seq": c.seq,
                        "t_s": _finite(c.t_s),
                        "command": c.command,
                        "term": c.term,
                        "terms_before": None if c.terms_before is None else list(c.terms_before),
                        "terms_after": None if c.terms_after is None else list(c.terms_after),
                    }
                    for c in changes
                ]
            )
        self.state.store_state = "open"
        self.state.store_note = f"{reader.path} (read-only)"

    def _offsets_from_stored_curves(self) -> None:
        """A finished run: d(t) as the tip controller received it, rebuilt from the
        curves kept in the store, through the run's own safety limiter.

        The offset stream itself is not recorded; each stored curve is
        evaluated from its publication (the end of its frame) to the next one.
        Stale or paused stretches are not known afterwards and are not marked.
        """
        assert self._reader is not None
        curves: list[tuple[float, OffsetCurve]] = []
        for t_pub, doc in self._reader.stored_curves():
            try:
                curves.append((t_pub, OffsetCurve.from_dict(doc)))
            except InputError as err:
                log.warning(
                    "%s: a stored offset curve is unusable (%s); skipped", self.run_dir, err
                )
        if not curves:
            return
        service = self._registration_config.service
        limiter = OffsetLimiter(
            max_offset_nm=service.max_offset_nm, max_rate_nm_s=service.max_offset_rate_nm_s
        )
        t_first = curves[0][0]
        t_stop = max(curves[-1][1].t_valid_s[1], curves[-1][0])
        step = max((t_stop - t_first) / 4000.0, 0.5)
        start = curves[0][1].at([t_first])[0]
        limiter.hold(t_first, float(start[0]), float(start[1]))
        for k, (t0, curve) in enumerate(curves):
            t1 = curves[k + 1][0] if k + 1 < len(curves) else t_stop
            ts = np.arange(t0, t1, step)
            for t, (x, y) in zip(ts, curve.at(ts), strict=True):
                out = limiter.apply(float(t), float(x), float(y))
                self.state.offsets.add(float(t), (out.x_nm, out.y_nm), (False, out.clamped))
        self.state.offset_source = (
            f"rebuilt from the {len(curves)} offset curves kept in the run store, through "
            "its safety limits (the stream itself is not recorded; stale or paused "
            "stretches are not known afterwards)"
        )

    async def _poll_store(self) -> None:
        while True:
            await asyncio.sleep(self.store_poll_s)
            if self._reader is None:
                try:
                    self._open_store()
                except StoreNotReadyError as err:
                    # Not there yet, or removed: a live dashboard waits for it.
                    if self.pub_endpoint is not None and self.wait_for_store:
                        self._store_missing(err)
                    else:
                        self._store_unusable(err)
                    continue
                except DashboardError as err:
                    self._store_unusable(err)
                    continue
            try:
                await self._poll_store_once()
            except DashboardError as err:
                # A removed or damaged store: say so, reopen on the next poll.
                self._store_unusable(err)
                if self._reader is not None:
                    self._reader.close()
                    self._reader = None

    def _store_unusable(self, err: DashboardError) -> None:
        if str(err) != self.state.store_note:
            log.warning("%s", err)
        self.state.store_state = "error"
        self.state.store_note = str(err)

    # ------------------------------------------------------------------ pages

    async def _tick(self) -> None:
        n = 0
        while True:
            await asyncio.sleep(self.tick_s)
            n += 1
            due = n % max(1, round(2.0 / self.tick_s)) == 1
            if self.diagnosis is not None and due and await asyncio.to_thread(self.diagnosis.poll):
                self.state.diagnosis = self.diagnosis.result
                self.state.diagnosis_note = self.diagnosis.note
            live = self.live_diagnoses
            if live is not None and due and await asyncio.to_thread(live.poll):
                assert live.latest is not None
                self.state.add_live_diagnosis(live_finding(live.latest))
            if not self._pages:
                self._new_events.clear()
                continue
            self._broadcast(self._delta())

    def _delta(self) -> dict[str, Any]:
        env = self.state.offsets
        gen, sent_n = self._sent_offset
        start = 0 if gen != env.generation else max(0, sent_n - 1)
        offset = self.state.offset_json(start)
        self._sent_offset = (env.generation, env.n_bins)
        starts: dict[str, int] = {}
        for name, cenv in self.state.channels.items():
            cgen, cn = self._sent_channels.get(name, (-1, 0))
            starts[name] = 0 if cgen != cenv.generation else max(0, cn - 1)
            self._sent_channels[name] = (cenv.generation, cenv.n_bins)
        events, self._new_events = self._new_events, []
        return {
            "type": "tick",
            "offset": offset,
            "channels": self.state.channels_json(starts),
            "events": events,
            "summary": self.state.summary(
                now_wall_s=time.time(), silent_after_s=self.silent_after_s
            ),
        }

    # ------------------------------------------------------------------ frame view

    def _want_view(self) -> None:
        if self.state.frames:
            latest = next(reversed(self.state.frames))
            if latest != self._view_seq:
                self._view_wanted.set()

    async def _frame_views(self) -> None:
        while True:
            await self._view_wanted.wait()
            self._view_wanted.clear()
            if not self.state.frames:
                continue
            seq = next(reversed(self.state.frames))
            if seq == self._view_seq:
                continue
            self._view_seq = seq
            view = await asyncio.to_thread(self._compute_view, seq)
            if view is None:
                # Its store row (pixel size) is not read yet: the store poll asks again.
                self._view_seq = None
                continue
            self.state.frame_view = view
            self._broadcast({"type": "frame_view", "view": view})

    def _compute_view(self, seq: int) -> dict[str, Any] | None:
        row = self.state.frames.get(seq, {})
        base: dict[str, Any] = {"seq": seq}
        if row.get("reason") == "reference":
            return base | {"note": f"frame {seq} is the registration reference: no vectors"}
        current = self.images.load(seq)
        if current is None:
            return base | {"note": self.images.unavailable_reason()}
        ref_seq = None
        reference = None
        for s in range(seq - 1, max(-1, seq - 1 - _VIEW_LOOKBACK), -1):
            r = self.state.frames.get(s)
            if r is None or not r.get("valid"):
                continue
            reference = self.images.load(s)
            if reference is not None:
                ref_seq = s
                break
        if reference is None or ref_seq is None:
            return base | {"note": f"no earlier accepted frame with an image for frame {seq}"}
        if reference.shape != current.shape:
            return base | {"note": f"frame {seq} and frame {ref_seq} differ in shape"}
        px = row.get("pixel_x_nm") or row.get("pixel_y_nm")
        py = row.get("pixel_y_nm") or px
        if px is None or py is None or not (math.isfinite(px) and math.isfinite(py)):
            return None
        try:
            return frame_view(
                current,
                reference,
                seq=seq,
                reference_seq=ref_seq,
                pixel_size_nm=(float(px), float(py)),
                config=self._registration_config,
            )
        except AfmdriftError as err:
            return base | {"note": f"re-measurement failed: {err}"}


def _resource(name: str) -> bytes:
    return (resources.files("afmdrift.dashboard") / "static" / name).read_bytes()


def _plotly_js() -> bytes:
    try:
        from plotly.offline import get_plotlyjs  # type: ignore[import-untyped]
    except ImportError as err:
        raise DashboardError(f"the dashboard needs the plotly package ({err})") from None
    text: str = get_plotlyjs()
    return text.encode("utf-8")


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _refuse(status: int, reason: str) -> web.StreamResponse:
    """A refused control request: its reason, as JSON, for the page to show."""
    log.warning("dashboard control request refused (%d): %s", status, reason)
    return web.json_response({"ok": False, "error": reason}, status=status)

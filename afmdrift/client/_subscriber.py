"""Subscribing to the drift service.

A :class:`Subscriber` receives the ``offset``, ``model``, ``frame`` and
``status`` topics (wire format v1, ``docs/wire.md``). Besides handing over
the messages it keeps the latest model, so a controller can evaluate d(t)
itself at its own rate and time with :meth:`Subscriber.offset_at`, and it
tells whether what it holds is still trustworthy (:meth:`Subscriber.is_stale`).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zmq
import zmq.asyncio
import zmq.auth

from afmdrift.errors import AfmdriftError
from afmdrift.model import OffsetCurve
from afmdrift.wire import (
    TOPICS,
    ControlReply,
    DiagnosisMsg,
    FrameMsg,
    ModelMsg,
    OffsetMsg,
    Published,
    StatusMsg,
    control_request,
    decode,
    decode_control_reply,
)

__all__ = [
    "ClientError",
    "ControlRefusedError",
    "CurveClientKeys",
    "NoModelError",
    "Subscriber",
    "control",
    "subscribe",
]

Message = Published


class ClientError(AfmdriftError):
    """The service did not answer in time, or answered with an error."""


class NoModelError(ClientError):
    """No ``model`` message has been received yet, so d(t) cannot be evaluated."""


class CurveClientKeys:
    """Client side of CURVE: the server's public key and the client's key pair."""

    def __init__(self, *, server_public_key_file: str | Path, client_secret_key_file: str | Path):
        server_public, _ = zmq.auth.load_certificate(str(server_public_key_file))
        public, secret = zmq.auth.load_certificate(str(client_secret_key_file))
        if secret is None:
            raise ClientError(f"{client_secret_key_file}: holds no secret key")
        self.server_public = server_public
        self.public = public
        self.secret = secret

    def apply(self, sock: zmq.asyncio.Socket) -> None:
        sock.curve_serverkey = self.server_public
        sock.curve_publickey = self.public
        sock.curve_secretkey = self.secret


class Subscriber:
    """SUB socket on the service's PUB endpoint; keeps the latest of each topic.

    Parameters
    ----------
    endpoint : str
        The service's ``pub_endpoint`` (e.g. ``tcp://127.0.0.1:5560``).
    topics : sequence of str
        Topics to receive (default: all).
    ctx : zmq.asyncio.Context, optional
        Context for the socket (default: the process-wide instance).
    curve : CurveClientKeys, optional
        Keys when the service publishes off loopback (CURVE).

    Attributes
    ----------
    model, status, offset, frame, diagnosis : message or None
        The latest message received on each topic.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        topics: Sequence[str] = TOPICS,
        ctx: zmq.asyncio.Context | None = None,
        curve: CurveClientKeys | None = None,
    ) -> None:
        unknown = [t for t in topics if t not in TOPICS]
        if unknown:
            raise ValueError(f"unknown topic(s) {unknown} (known: {', '.join(TOPICS)})")
        self._ctx = ctx or zmq.asyncio.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        if curve is not None:
            curve.apply(self._sock)
        for t in topics:
            self._sock.setsockopt(zmq.SUBSCRIBE, t.encode("ascii"))
        self._sock.connect(endpoint)
        self.endpoint = endpoint
        self.model: ModelMsg | None = None
        self.status: StatusMsg | None = None
        self.offset: OffsetMsg | None = None
        self.frame: FrameMsg | None = None
        self.diagnosis: DiagnosisMsg | None = None
        self.last_received_wall_s: float | None = None
        self.received = 0
        self._curve: Any = None

    async def recv(self, *, timeout_s: float | None = None) -> Message:
        """The next message (raises :class:`TimeoutError` after ``timeout_s``)."""
        parts = await asyncio.wait_for(self._sock.recv_multipart(), timeout_s)
        msg = decode(parts)
        self.received += 1
        self.last_received_wall_s = time.time()
        if isinstance(msg, ModelMsg):
            self.model = msg
            self._curve = None
        elif isinstance(msg, StatusMsg):
            self.status = msg
        elif isinstance(msg, OffsetMsg):
            self.offset = msg
        elif isinstance(msg, DiagnosisMsg):
            self.diagnosis = msg
        else:
            self.frame = msg
        return msg

    def __aiter__(self) -> Subscriber:
        return self

    async def __anext__(self) -> Message:
        return await self.recv()

    def instrument_time(self, wall_s: float | None = None) -> float:
        """Instrument time at Unix time ``wall_s`` (default now), from the latest model."""
        if self.model is None:
            raise NoModelError("no model received yet: the instrument clock is unknown")
        return self.model.clock.instrument_at(time.time() if wall_s is None else wall_s)

    def offset_at(self, t_s: float | None = None) -> tuple[float, float]:
        """d(t) in nm from the latest model at instrument time ``t_s`` (default: now).

        This is the model's curve itself; the service's ``offset`` topic also
        applies the rate and magnitude limits (given in the model message).

        Raises
        ------
        NoModelError
            No model message has been received yet.
        """
        if self.model is None:
            raise NoModelError("no model received yet; wait for a 'model' message")
        if self._curve is None:
            self._curve = OffsetCurve.from_dict(self.model.curve)
        t = self.instrument_time() if t_s is None else t_s
        value = self._curve.at([t])
        flat = [float(v) for v in value.reshape(-1)[:2]]
        x, y = flat[0], flat[1]
        limit = self.model.max_offset_nm
        r = math.hypot(x, y)
        if r > limit:
            x, y = x * limit / r, y * limit / r
        return x, y

    def is_stale(self, *, max_silence_s: float = 5.0, wall_s: float | None = None) -> bool:
        """True when the latest information should not be used.

        That is: nothing received for ``max_silence_s`` wall seconds, no model
        yet, the service's status reports ``stale``, or the latest offset
        sample was marked invalid.
        """
        now = time.time() if wall_s is None else wall_s
        if self.last_received_wall_s is None or now - self.last_received_wall_s > max_silence_s:
            return True
        if self.model is None:
            return True
        if self.status is not None and (
            "stale" in self.status.flags or self.status.state == "stale"
        ):
            return True
        return self.offset is not None and not self.offset.valid

    def close(self) -> None:
        self._sock.close(linger=0)

    async def __aenter__(self) -> Subscriber:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


def subscribe(
    endpoint: str,
    *,
    topics: Sequence[str] = TOPICS,
    ctx: zmq.asyncio.Context | None = None,
    curve: CurveClientKeys | None = None,
) -> Subscriber:
    """Connect a :class:`Subscriber` to the service's PUB endpoint."""
    return Subscriber(endpoint, topics=topics, ctx=ctx, curve=curve)


async def control(
    endpoint: str,
    cmd: str,
    *,
    config_path: str | None = None,
    term: str | None = None,
    token: str | None = None,
    token_file: str | Path | None = None,
    timeout_s: float = 5.0,
    ctx: zmq.asyncio.Context | None = None,
    curve: CurveClientKeys | None = None,
) -> ControlReply:
    """Send one command to the control socket and return the reply.

    ``cmd`` is ``status``, ``diagnose`` (start a live diagnosis; the reply says
    whether it ``started``), ``model`` (the reply carries the current model
    message), ``pause``, ``resume``, ``reset_reference``, ``reload_model``
    (with an optional ``config_path``), ``add_term`` or ``remove_term``
    (with ``term``). All but ``status``, ``diagnose`` and ``model`` need the daemon's
    token: pass it, or the file the daemon wrote it to (``token_file``,
    default for a daemon: ``RUN_DIR/control.token``).

    Raises
    ------
    ControlRefusedError
        The service answered ``ok: false`` (its reason in the message and
        in :attr:`ControlRefusedError.reply`).
    ClientError
        The token file cannot be read, or no reply came within ``timeout_s``.
    WireError
        The request is not a valid one (an unknown command, a field too long).
    """
    if token is None and token_file is not None:
        token = await asyncio.to_thread(_read_token, cmd, Path(token_file))
    request = control_request(cmd=cmd, config_path=config_path, term=term, token=token)
    context = ctx or zmq.asyncio.Context.instance()
    sock = context.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    if curve is not None:
        curve.apply(sock)
    try:
        sock.connect(endpoint)
        await sock.send(request.model_dump_json().encode("utf-8"))
        try:
            payload = await asyncio.wait_for(sock.recv(), timeout_s)
        except TimeoutError:
            raise ClientError(
                f"control {cmd!r}: no reply from {endpoint} within {timeout_s} s"
            ) from None
    finally:
        sock.close(linger=0)
    reply = decode_control_reply(payload)
    if not reply.ok:
        raise ControlRefusedError(f"control {cmd!r} refused: {reply.error}", reply)
    return reply


class ControlRefusedError(ClientError):
    """The service answered a control command with ``ok: false``."""

    def __init__(self, message: str, reply: ControlReply) -> None:
        super().__init__(message)
        #: The service's reply (``error`` says why).
        self.reply = reply


def _read_token(cmd: str, path: Path) -> str:
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeError) as err:
        raise ClientError(f"control {cmd!r}: cannot read token file {path}: {err}") from None

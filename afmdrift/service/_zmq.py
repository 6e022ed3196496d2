"""ZeroMQ sockets of the service: the publisher, the control socket, CURVE security.

Sockets are created on a :class:`zmq.asyncio.Context` that the caller may pass
in (tests and embedding applications share theirs); otherwise the service
creates and terminates its own. A PUB socket never blocks on a slow or absent
subscriber: messages beyond the high-water mark are dropped for that
subscriber only.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.asyncio
import zmq.auth
from zmq.auth.asyncio import AsyncioAuthenticator

from afmdrift.config import ServiceConfig, endpoint_is_local
from afmdrift.errors import AfmdriftError
from afmdrift.wire import (
    ControlReply,
    ControlRequest,
    Published,
    WireError,
    decode_control_request,
    encode,
)

__all__ = [
    "ControlMessage",
    "ControlSocket",
    "CurveKeys",
    "Publisher",
    "ServiceSocketError",
    "load_curve_keys",
]

log = logging.getLogger(__name__)

#: Seconds between warnings about rejected control messages.
_WARN_EVERY_S = 10.0


class ServiceSocketError(AfmdriftError):
    """A socket cannot be bound or secured as configured; the message names the key."""


class CurveKeys:
    """Server keys and the authenticator that admits configured client keys."""

    def __init__(self, *, public: bytes, secret: bytes, clients_dir: Path) -> None:
        self.public = public
        self.secret = secret
        self.clients_dir = clients_dir
        self._auth: AsyncioAuthenticator | None = None

    def start(self, ctx: zmq.asyncio.Context) -> None:
        """Start the ZAP authenticator on ``ctx`` admitting the clients' public keys."""
        self._auth = AsyncioAuthenticator(ctx)
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(self.clients_dir))

    def apply(self, sock: zmq.asyncio.Socket) -> None:
        sock.curve_secretkey = self.secret
        sock.curve_publickey = self.public
        sock.curve_server = True

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None


def load_curve_keys(config: ServiceConfig) -> CurveKeys | None:
    """CURVE keys when any endpoint is not loopback, else ``None``.

    Raises
    ------
    ServiceSocketError
        Keys are required but missing or unreadable; the message names the key.
    """
    exposed = [
        k for k in ("pub_endpoint", "control_endpoint") if not endpoint_is_local(getattr(config, k))
    ]
    if not exposed:
        return None
    if config.curve_secret_key_file is None or config.curve_authorized_clients_dir is None:
        raise ServiceSocketError(
            f"service.{exposed[0]} is not a loopback address; set service.curve_secret_key_file "
            "and service.curve_authorized_clients_dir"
        )
    key_file = Path(config.curve_secret_key_file)
    try:
        public, secret = zmq.auth.load_certificate(key_file)
    except (OSError, ValueError) as err:
        raise ServiceSocketError(
            f"service.curve_secret_key_file {str(key_file)!r}: cannot read a CURVE "
            f"certificate ({err})"
        ) from None
    if secret is None:
        raise ServiceSocketError(
            f"service.curve_secret_key_file {str(key_file)!r} holds no secret key "
            "(use the .key_secret file from zmq.auth.create_certificates)"
        )
    clients = Path(config.curve_authorized_clients_dir)
    if not clients.is_dir():
        raise ServiceSocketError(
            f"service.curve_authorized_clients_dir {str(clients)!r} is not a directory"
        )
    return CurveKeys(public=public, secret=secret, clients_dir=clients)


def _bind(
    ctx: zmq.asyncio.Context,
    kind: int,
    endpoint: str,
    key: str,
    curve: CurveKeys | None,
    options: dict[int, int] | None = None,
) -> zmq.asyncio.Socket:
    """A socket of ``kind`` bound to ``endpoint``; ``options`` are set before the
    bind (ZeroMQ applies most options only to connections made after them)."""
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for option, value in (options or {}).items():
        sock.setsockopt(option, value)
    if curve is not None and not endpoint_is_local(endpoint):
        curve.apply(sock)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as err:
        sock.close()
        raise ServiceSocketError(f"service.{key} {endpoint!r}: cannot bind ({err})") from None
    return sock


class Publisher:
    """PUB socket for the topics (``afmdrift.wire.TOPICS``).

    Parameters
    ----------
    endpoint : str
        Bind endpoint, e.g. ``tcp://127.0.0.1:5560`` (``tcp://127.0.0.1:*`` picks
        a free port; see :attr:`endpoint`).
    ctx : zmq.asyncio.Context, optional
        Context to create the socket on (default: the process-wide instance).
    sndhwm : int
        Messages queued per subscriber before further ones are dropped.
    curve : CurveKeys, optional
        Server keys, applied when the endpoint is not loopback.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        ctx: zmq.asyncio.Context | None = None,
        sndhwm: int = 10000,
        curve: CurveKeys | None = None,
    ) -> None:
        self._ctx = ctx or zmq.asyncio.Context.instance()
        self._sock = _bind(
            self._ctx, zmq.PUB, endpoint, "pub_endpoint", curve, {zmq.SNDHWM: sndhwm}
        )
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.sent = 0
        self.dropped = 0

    async def send(self, msg: Published) -> None:
        """Publish ``msg`` without ever waiting for subscribers."""
        try:
            await self._sock.send_multipart(encode(msg), flags=zmq.NOBLOCK)
            self.sent += 1
        except zmq.Again:
            self.dropped += 1

    def close(self) -> None:
        self._sock.close(linger=0)


@dataclass(frozen=True, slots=True)
class ControlMessage:
    """One message received on the control socket, with its route back.

    ``request`` is the decoded request, or ``None`` when the message was not
    one (then ``error`` says why and the reply is an error).
    """

    envelope: tuple[bytes, ...]
    request: ControlRequest | None
    error: str | None = None


class ControlSocket:
    """The control socket: any peer's request gets exactly one reply.

    A ROUTER socket, so a malformed peer cannot wedge it the way it wedges a
    REP socket: a REQ client's message is ``[identity, b"", request]`` and its
    reply goes back behind the same envelope; a DEALER peer that sends
    ``[request]`` without the empty delimiter gets ``[reply]`` the same way; a
    request of several frames gets an error reply. Messages over
    ``max_request_bytes`` are dropped by ZeroMQ itself (the peer is
    disconnected) before they take memory.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        ctx: zmq.asyncio.Context | None = None,
        curve: CurveKeys | None = None,
        max_request_bytes: int = 65536,
    ) -> None:
        self._ctx = ctx or zmq.asyncio.Context.instance()
        # MAXMSGSIZE applies to each frame, before it is read into memory.
        self._sock = _bind(
            self._ctx,
            zmq.ROUTER,
            endpoint,
            "control_endpoint",
            curve,
            {zmq.MAXMSGSIZE: max_request_bytes},
        )
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self._last_warning_s = -math.inf
        self._suppressed = 0

    async def receive(self) -> ControlMessage:
        """The next message, decoded, with the envelope its reply must carry."""
        frames = await self._sock.recv_multipart()
        identity, rest = frames[0], frames[1:]
        envelope: tuple[bytes, ...]
        if rest and rest[0] == b"":
            envelope, body = (identity, b""), rest[1:]
        else:
            envelope, body = (identity,), rest
        if len(body) != 1:
            error = f"control request: expected one frame, got {len(body)}"
            self._rejected(error)
            return ControlMessage(envelope, None, error)
        try:
            return ControlMessage(envelope, decode_control_request(body[0]))
        except WireError as err:
            self._rejected(str(err))
            return ControlMessage(envelope, None, str(err))

    def _rejected(self, error: str) -> None:
        """Log a rejected message; a flood of them (any local process can send
        one) gives one warning per ``_WARN_EVERY_S`` with the count, not one each."""
        now = time.monotonic()
        self._suppressed += 1
        if now - self._last_warning_s < _WARN_EVERY_S:
            return
        more = (
            f" (and {self._suppressed - 1} more since the last warning)"
            if self._suppressed > 1
            else ""
        )
        log.warning("control: rejected a message: %s%s", error, more)
        self._last_warning_s = now
        self._suppressed = 0

    async def reply(self, message: ControlMessage, reply: ControlReply) -> None:
        """Send ``reply`` back along ``message``'s envelope (never blocks; a peer
        that has gone is skipped)."""
        payload = reply.model_dump_json().encode("utf-8")
        try:
            await self._sock.send_multipart([*message.envelope, payload], flags=zmq.NOBLOCK)
        except zmq.ZMQError as err:
            log.warning("control: reply not sent: %s", err)

    def close(self) -> None:
        self._sock.close(linger=0)

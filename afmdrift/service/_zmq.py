"""ZeroMQ sockets of the service: the publisher, the control socket, CURVE security.

Sockets are created on a :class:`zmq.asyncio.Context` that the caller may pass
in (tests and embedding applications share theirs); otherwise the service
creates and terminates its own. A PUB socket never blocks on a slow or absent
subscriber: messages beyond the high-water mark are dropped for that
subscriber only.
"""

from __future__ import annotations

import logging
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
    FrameMsg,
    ModelMsg,
    OffsetMsg,
    StatusMsg,
    WireError,
    decode_control_request,
    encode,
)

__all__ = ["ControlSocket", "CurveKeys", "Publisher", "ServiceSocketError", "load_curve_keys"]

log = logging.getLogger(__name__)


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
    ctx: zmq.asyncio.Context, kind: int, endpoint: str, key: str, curve: CurveKeys | None
) -> zmq.asyncio.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    if curve is not None and not endpoint_is_local(endpoint):
        curve.apply(sock)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as err:
        sock.close()
        raise ServiceSocketError(f"service.{key} {endpoint!r}: cannot bind ({err})") from None
    return sock


class Publisher:
    """PUB socket for the four topics.

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
        self._sock = _bind(self._ctx, zmq.PUB, endpoint, "pub_endpoint", curve)
        self._sock.setsockopt(zmq.SNDHWM, sndhwm)
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.sent = 0
        self.dropped = 0

    async def send(self, msg: OffsetMsg | ModelMsg | FrameMsg | StatusMsg) -> None:
        """Publish ``msg`` without ever waiting for subscribers."""
        try:
            await self._sock.send_multipart(encode(msg), flags=zmq.NOBLOCK)
            self.sent += 1
        except zmq.Again:
            self.dropped += 1

    def close(self) -> None:
        self._sock.close(linger=0)


class ControlSocket:
    """REP socket answering :class:`ControlRequest` messages."""

    def __init__(
        self,
        endpoint: str,
        *,
        ctx: zmq.asyncio.Context | None = None,
        curve: CurveKeys | None = None,
    ) -> None:
        self._ctx = ctx or zmq.asyncio.Context.instance()
        self._sock = _bind(self._ctx, zmq.REP, endpoint, "control_endpoint", curve)
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)

    async def receive(self) -> ControlRequest | ControlReply:
        """The next request, or a ready error reply when the request is malformed."""
        payload = await self._sock.recv()
        try:
            return decode_control_request(payload)
        except WireError as err:
            log.warning("control: rejected request: %s", err)
            return ControlReply(ok=False, error=str(err))

    async def reply(self, reply: ControlReply) -> None:
        await self._sock.send(reply.model_dump_json().encode("utf-8"))

    def close(self) -> None:
        self._sock.close(linger=0)

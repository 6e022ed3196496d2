"""The control socket's commands, who may give them, and what ``reload_model`` may read.

Trust model (``docs/service.md``, *Control socket*):

* Any local process can connect to a loopback endpoint, so commands that
  change the daemon's state (``pause``, ``resume``, ``reset_reference``,
  ``reload_model``, ``add_term``, ``remove_term``; :data:`STATE_CHANGING`)
  need a token: a random string the daemon writes at start
  to ``service.control_token_file`` (default ``RUN_DIR/control.token``),
  readable only by the daemon's user. ``status`` and ``model`` only read;
  ``diagnose`` starts a live diagnosis (a child process at the lowest CPU
  priority, at most one at a time), which changes nothing the daemon
  measures or publishes, so it needs no token either.
  ``control_auth = false`` turns the check off; endpoints off loopback
  require CURVE as well.
* ``reload_model`` reads only regular files in the directory of the daemon's
  own configuration file or in ``service.reload_config_dir``, at most
  :data:`~afmdrift.config.MAX_CONFIG_BYTES`, in the worker thread (never on
  the event loop). Configuration files are trusted input: effect plugins
  they name are imported.
* Every message gets exactly one reply; no message, however malformed, ends
  the control task.

Model changes (``reload_model``, ``add_term``, ``remove_term``) run in the
worker thread, so they fall between two frames: the new predictor is fitted
on the kept history, the change is committed to the run store (a store that
cannot write refuses the change: it would not outlive a restart), and only
then does the pipeline predict with it, d(t) handing over without a step
(:meth:`~afmdrift.pipeline.FramePipeline.use_model`). A refused change
leaves everything as it was.
"""

from __future__ import annotations

import hmac
import logging
import os
import secrets
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Literal, Protocol, TypeVar

from afmdrift.config import AfmdriftConfig, ModelConfig, load_config
from afmdrift.errors import AfmdriftError, ConfigError
from afmdrift.model import Predictor, make_predictor
from afmdrift.pipeline import FramePipeline
from afmdrift.runs import TERM_COMMANDS, ModelChange, change_terms, model_terms
from afmdrift.service._publish import Publishing
from afmdrift.service._zmq import ControlMessage, ControlSocket
from afmdrift.wire import STATE_CHANGING, ControlReply, ControlRequest

__all__ = ["STATE_CHANGING", "Controller", "write_token"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")


class InWorker(Protocol):
    """Runs a function in the daemon's worker thread."""

    def __call__(self, fn: Callable[[], _T], /) -> Awaitable[_T]: ...


def write_token(path: Path) -> str:
    """Write a new random token to ``path`` (mode 0600, atomically); return it.

    Raises
    ------
    OSError
        ``path``'s directory does not exist (it is not created) or cannot be
        written; nothing is left behind.
    """
    token = secrets.token_urlsafe(32)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        try:
            os.fchmod(fd, 0o600)
            os.write(fd, token.encode("ascii"))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return token


class Controller:
    """Answers control messages for a daemon.

    Parameters
    ----------
    config : AfmdriftConfig
        The daemon's configuration (``service`` settings; ``model`` is
        replaced by ``reload_model``).
    config_path : Path or None
        The daemon's configuration file (``reload_model`` without a path
        re-reads it; its directory is one where others may be read).
    pipeline : FramePipeline
    publishing : Publishing
    in_worker : callable
        Runs a function in the daemon's worker thread.
    record_change : callable
        Commits a :class:`~afmdrift.runs.ModelChange` to the run store (in
        the worker thread); raises :class:`~afmdrift.errors.AfmdriftError`
        when the store cannot write.
    diagnose : callable, optional
        Starts a live diagnosis (``diagnose``); returns whether it started.
    """

    def __init__(
        self,
        *,
        config: AfmdriftConfig,
        config_path: Path | None,
        pipeline: FramePipeline,
        publishing: Publishing,
        in_worker: InWorker,
        record_change: Callable[[ModelChange], None],
        diagnose: Callable[[Literal["request"]], bool] | None = None,
    ) -> None:
        self.config = config
        self.config_path = config_path
        self.pipeline = pipeline
        self.publishing = publishing
        self._in_worker = in_worker
        self._diagnose = diagnose
        self._record_change = record_change
        publishing.terms = model_terms(config.model)
        svc = config.service
        self.token_path = svc.token_path
        self._token: str | None = None
        dirs = [config_path.resolve().parent] if config_path is not None else []
        if svc.reload_config_dir is not None:
            dirs.append(Path(svc.reload_config_dir).resolve())
        self._reload_dirs = dirs

    def start(self) -> None:
        """Write the token file (when commands need a token).

        Raises
        ------
        ConfigError
            The token file cannot be written (no such directory, not a
            directory, not writable), naming ``service.control_token_file``.
        """
        if self.config.service.control_auth:
            try:
                self._token = write_token(self.token_path)
            except OSError as err:
                folder = self.token_path.parent
                if isinstance(err, FileNotFoundError):
                    why = f"no directory {folder}"
                elif isinstance(err, NotADirectoryError):
                    why = f"{folder} is not a directory"
                else:
                    why = f"{err.strerror or err} in {folder}"
                raise ConfigError(
                    f"service.control_token_file {self.token_path}: cannot write the control "
                    f"token ({why})"
                ) from None
            log.info("control token written to %s", self.token_path)

    def stop(self) -> None:
        """Remove the token file this daemon wrote."""
        if self._token is not None:
            self.token_path.unlink(missing_ok=True)
            self._token = None

    async def serve(self, sock: ControlSocket) -> None:
        """Answer every message on ``sock``, for ever."""
        while True:
            message = await sock.receive()
            await sock.reply(message, await self.answer(message))

    async def answer(self, message: ControlMessage) -> ControlReply:
        """The reply to one message; an error reply for anything that goes wrong."""
        req = message.request
        if req is None:
            return ControlReply(ok=False, error=message.error)
        try:
            return await self._handle(req)
        except AfmdriftError as err:
            return ControlReply(ok=False, error=str(err))
        except Exception as err:  # a bug must not end the control task; it is logged
            log.exception("control: %s failed", req.cmd)
            return ControlReply(ok=False, error=f"{req.cmd}: internal error: {type(err).__name__}")

    async def _handle(self, req: ControlRequest) -> ControlReply:
        log.info("control: %s", req.cmd)
        if req.cmd in STATE_CHANGING:
            self._authorise(req)
        if req.cmd == "pause":
            self.publishing.paused = True
        elif req.cmd == "resume":
            self.publishing.paused = False
        elif req.cmd == "reset_reference":
            self.pipeline.request_reset()
        elif req.cmd == "reload_model":
            await self._reload_model(req.config_path)
        elif req.cmd == "diagnose":
            if self._diagnose is None:
                raise AfmdriftError("diagnose: this daemon has no live diagnosis")
            started = self._diagnose("request")
            return ControlReply(ok=True, status=self.publishing.status_snapshot(), started=started)
        elif req.cmd in TERM_COMMANDS:
            await self._change_terms(req.cmd, req.term)
        elif req.cmd == "model":
            return ControlReply(
                ok=True,
                status=self.publishing.status_snapshot(),
                model=self.publishing.last_model,
            )
        return ControlReply(ok=True, status=self.publishing.status_snapshot())

    def _authorise(self, req: ControlRequest) -> None:
        if self._token is None:
            return
        given = (req.token or "").encode("utf-8", "replace")
        if not hmac.compare_digest(given, self._token.encode("ascii")):
            what = "a wrong token" if req.token else "no token"
            raise AfmdriftError(
                f"{req.cmd}: refused, {what}: state-changing commands need the token in "
                f"{self.token_path}"
            )

    def _allowed_path(self, config_path: str | None) -> Path:
        if config_path is None:
            if self.config_path is None:
                raise AfmdriftError(
                    "reload_model: the daemon was started without a configuration file; "
                    "name one in config_path"
                )
            return self.config_path
        try:
            os.fsencode(config_path)
        except UnicodeError:
            raise ConfigError("reload_model: config_path is not a valid file name") from None
        if "\x00" in config_path:
            raise ConfigError("reload_model: config_path is not a valid file name")
        resolved = Path(config_path).resolve()
        if not any(resolved.is_relative_to(d) for d in self._reload_dirs):
            allowed = ", ".join(str(d) for d in self._reload_dirs) or "none configured"
            raise ConfigError(
                f"reload_model: {config_path!r} is outside the directories configuration "
                f"files may be reloaded from ({allowed}; see service.reload_config_dir)"
            )
        return resolved

    async def _reload_model(self, config_path: str | None) -> None:
        path = self._allowed_path(config_path)

        def reload() -> tuple[ModelConfig, int]:
            new = load_config(path)  # a regular file of bounded size, UTF-8 (read_toml)
            predictor = make_predictor(new.model.predictor, new.model)
            return new.model, self._use(new.model, predictor, "reload_model", None)

        model, n = await self._in_worker(reload)
        await self._changed(model)
        log.info("reloaded [model] from %s (%s), refitted on %d points", path, model.predictor, n)

    async def _change_terms(self, cmd: str, term: str | None) -> None:
        if term is None:
            raise ConfigError(f"{cmd}: needs 'term' (a term name or spec, docs/model.md)")

        def change() -> tuple[ModelConfig, int]:
            model, predictor = change_terms(self.config.model, cmd, term)
            return model, self._use(model, predictor, cmd, term.strip())

        model, n = await self._in_worker(change)
        await self._changed(model)
        log.info(
            "%s %r: terms now %s, refitted on %d points", cmd, term.strip(),
            model.physics.terms, n,
        )  # fmt: skip

    def _use(self, model: ModelConfig, predictor: Predictor, cmd: str, term: str | None) -> int:
        """In the worker, between two frames: fit ``predictor`` on the kept
        history, commit the change to the run store, then predict with it.
        Nothing changes when the fit or the store fails."""
        n = self.pipeline.refit(predictor)
        now = time.time()
        t_now = self.publishing.clock.at(now)
        plan = None
        if t_now is not None:
            # Offset samples are 1/offset_rate_hz apart in wall time; the bound
            # holds for two such periods (a sample one period late), on the
            # instrument's clock.
            clock = self.publishing.clock
            interval_s = clock.rate * 2.0 / self.config.service.offset_rate_hz
            plan = self.pipeline.plan_handover(
                predictor,
                t_now_s=t_now,
                sample_interval_s=interval_s,
                lead_s=clock.rate * HANDOVER_LEAD_WALL_S,
            )
        handed = plan is not None and plan.curve is not None
        try:
            self._record_change(
                ModelChange(
                    seq=self.pipeline.last_seq,
                    t_s=float("nan") if t_now is None else t_now,
                    wall_s=now,
                    command=cmd,
                    term=term,
                    predictor=model.predictor,
                    terms_before=_terms(self.config.model),
                    terms_after=_terms(model),
                    handover_until_s=plan.until_s if plan and handed else float("nan"),
                    step_bound_nm=plan.bound_nm if plan and handed else float("nan"),
                )
            )
        except AfmdriftError as err:
            raise AfmdriftError(f"{cmd}: refused, nothing changed: {err}") from None
        self.pipeline.use_model(predictor, plan)
        return n

    async def _changed(self, model: ModelConfig) -> None:
        """Take up the model the worker now predicts with (on the event loop)."""
        self.config = self.config.model_copy(update={"model": model})
        self.pipeline.config = self.config
        self.publishing.terms = model_terms(model)
        if self.pipeline.curve is not None:
            await self.publishing.model_changed(
                self.pipeline.curve, self.pipeline.predictor.name, self.pipeline.last_seq
            )


#: Wall seconds for which d(t) after a model change stays the published curve
#: before it hands over (:meth:`FramePipeline.plan_handover` ``lead_s``, on the
#: instrument's clock): the offset stream takes the new curve up after the
#: store's commit and a pass of the event loop (0.65 s was seen on a loaded
#: 2-core machine), and taken up anywhere before the lead it has no step.
HANDOVER_LEAD_WALL_S = 2.0


def _terms(model: ModelConfig) -> tuple[str, ...] | None:
    terms = model_terms(model)
    return None if terms is None else tuple(terms)

"""Starting the daemon: the instrument from configuration, signals, exit codes."""

from __future__ import annotations

import asyncio
import logging
import signal
from collections.abc import Callable
from pathlib import Path

import zmq.asyncio
from pydantic import ValidationError

from afmdrift.config import AfmdriftConfig, DriverConfig
from afmdrift.drivers import Instrument, instrument_from_config
from afmdrift.errors import AfmdriftError, ConfigError
from afmdrift.model import Predictor
from afmdrift.pipeline import FramePipeline
from afmdrift.service._daemon import DriftService

__all__ = ["open_instrument", "run_until_signalled"]

log = logging.getLogger(__name__)


def open_instrument(config: AfmdriftConfig, *, url: str | None = None) -> Instrument:
    """The (unconnected) instrument of the ``[driver]`` section, or at ``url``.

    ``url`` replaces ``driver.transport`` (``socket://127.0.0.1:N``, a serial or
    pty path, or ``replay:SESSION_DIR``); the other driver settings still apply.
    """
    driver = config.driver
    if url is not None:
        try:
            driver = DriverConfig.model_validate({**driver.model_dump(), "transport": url})
        except ValidationError as err:
            raise ConfigError(f"--instrument {url!r}: {err.errors()[0]['msg']}") from None
    return instrument_from_config(driver)


async def run_until_signalled(
    *,
    config: AfmdriftConfig,
    instrument: Instrument,
    config_path: str | Path | None = None,
    ctx: zmq.asyncio.Context | None = None,
    predictor: Predictor | None = None,
    on_ready: Callable[[DriftService], None] | None = None,
    on_stop: Callable[[DriftService], None] | None = None,
) -> int:
    """Run :class:`DriftService` until SIGINT or SIGTERM; return the exit code.

    A signal cancels the service task; its ``finally`` closes the instrument,
    the sockets and the store. A task that died is reported and gives exit 1.
    ``on_ready`` is given the service once its sockets are bound and its
    store is open (what ``afmdrift run`` says it serves), ``on_stop`` after
    it has stopped, if it was ready, however it stopped.
    """
    loop = asyncio.get_running_loop()
    pipeline = FramePipeline(config=config, predictor=predictor)
    service = DriftService(
        config=config, instrument=instrument, ctx=ctx, config_path=config_path, pipeline=pipeline
    )
    task = asyncio.create_task(service.run(), name="afmdrift-service")
    announce = asyncio.create_task(_when_ready(service, on_ready), name="afmdrift-ready")
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, task.cancel)
    try:
        await task
    except asyncio.CancelledError:
        log.info("drift service stopped by signal")
        return 0
    except BaseExceptionGroup as group:
        # A task died (already logged with its traceback). A deliberate error
        # is reported as one message by the command line; anything else is a bug.
        deliberate = [e for e in group.exceptions if isinstance(e, AfmdriftError)]
        if deliberate:
            raise deliberate[0] from None
        raise
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        announce.cancel()
        await asyncio.gather(announce, return_exceptions=True)
        if on_stop is not None and service.ready.is_set():
            on_stop(service)
    return 0


async def _when_ready(
    service: DriftService, on_ready: Callable[[DriftService], None] | None
) -> None:
    await service.ready.wait()
    if on_ready is not None:
        on_ready(service)

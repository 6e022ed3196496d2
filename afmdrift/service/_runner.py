"""Starting the daemon: the instrument from configuration, signals, exit codes."""

from __future__ import annotations

import asyncio
import importlib
import logging
import signal
from pathlib import Path

import zmq.asyncio

from afmdrift.config import AfmdriftConfig
from afmdrift.drivers._base import Instrument
from afmdrift.errors import AfmdriftError, ConfigError
from afmdrift.service._daemon import DriftService

__all__ = ["open_instrument", "run_until_signalled"]

log = logging.getLogger(__name__)


def open_instrument(config: AfmdriftConfig, *, url: str | None = None) -> Instrument:
    """The (unconnected) instrument named by ``url`` or by the ``[driver]`` section.

    ``replay:SESSION_DIR`` replays a recorded session; anything else is a
    transport URL for the NanoScope-style driver (``socket://127.0.0.1:N``,
    ``/dev/ttyUSB0``, a pseudo-terminal path).

    Raises
    ------
    ConfigError
        No instrument is configured.
    """
    driver_cfg = getattr(config, "driver", None)
    target = url if url is not None else getattr(driver_cfg, "transport", None)
    if not target:
        raise ConfigError(
            "no instrument: set driver.transport in the configuration or pass --instrument URL"
        )
    if target.startswith("replay:"):
        replay = importlib.import_module("afmdrift.drivers._replay")
        speed = float(getattr(driver_cfg, "replay_speed", 1.0) or 1.0)
        instrument: Instrument = replay.ReplayInstrument(target[len("replay:") :], speed=speed)
        return instrument
    from afmdrift.drivers._nanoscope import NanoScopeDriver

    timeout = getattr(driver_cfg, "timeout_s", None)
    if timeout is None:
        return NanoScopeDriver(target)
    return NanoScopeDriver(target, timeout_s=timeout)


async def run_until_signalled(
    *,
    config: AfmdriftConfig,
    instrument: Instrument,
    config_path: str | Path | None = None,
    ctx: zmq.asyncio.Context | None = None,
) -> int:
    """Run :class:`DriftService` until SIGINT or SIGTERM; return the exit code.

    A signal cancels the service task; its ``finally`` closes the instrument,
    the sockets and the store. A task that died is reported and gives exit 1.
    """
    loop = asyncio.get_running_loop()
    service = DriftService(config=config, instrument=instrument, ctx=ctx, config_path=config_path)
    task = asyncio.create_task(service.run(), name="afmdrift-service")
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
    return 0

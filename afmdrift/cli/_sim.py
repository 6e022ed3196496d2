"""``afmdrift sim ...``: the simulated AFM behind the real wire protocol.

``afmdrift sim serve`` serves the protocol of ``docs/protocol.md`` on a
pseudo-terminal or on loopback TCP, backed by
:class:`afmdrift.drivers.sim.SimulatedAFM`.

Adding a subcommand to ``afmdrift sim``
---------------------------------------
Write a module (for example ``afmdrift/cli/_sim_record.py``) with a function::

    def register_sim_subcommand(ssub) -> None:
        p = ssub.add_parser("record", help="...", description="...")
        p.add_argument(...)
        p.set_defaults(handler=_record)   # handler(args) -> exit code

and append the module's name to :data:`SIM_SUBCOMMAND_MODULES` below (``record``
lives in ``afmdrift/cli/_sim_record.py`` this way). Keep heavy imports inside
the handler, as every CLI module does.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Any

#: Modules that add subcommands to ``afmdrift sim`` via ``register_sim_subcommand(ssub)``.
SIM_SUBCOMMAND_MODULES: tuple[str, ...] = ("afmdrift.cli._sim_record",)

#: Built-in scenario served when ``--scenario`` is not given (the paper's setting).
DEFAULT_SCENARIO = "graphite-paper"


def register(sub: Any) -> None:
    p = sub.add_parser(
        "sim",
        help="Run the simulated AFM.",
        description="The simulated AFM: serve it over the instrument protocol, record sessions.",
    )
    ssub = p.add_subparsers(dest="sim_command", metavar="ACTION")
    ssub.required = True
    _register_serve(ssub)
    for name in SIM_SUBCOMMAND_MODULES:
        importlib.import_module(name).register_sim_subcommand(ssub)


# --------------------------------------------------------------------------- serve


def _speed(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed must be a number, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"speed must be > 0, got {text!r}")
    return value


def _register_serve(ssub: Any) -> None:
    p = ssub.add_parser(
        "serve",
        help="Serve the simulated AFM over a pty or loopback TCP.",
        description="Serve the instrument protocol (docs/protocol.md) backed by the simulated "
        "AFM. With --pty the slave path (e.g. /dev/pts/5) is printed on stdout; with --port the "
        "bound TCP port on 127.0.0.1 is printed (--port 0 picks a free one), alone on the "
        "first line; stderr says what is served (scenario, protocol, address, speed-up). "
        "Connect with "
        "[driver] transport = that path or socket://127.0.0.1:PORT. With --protocol nanonis "
        "the same AFM speaks the Nanonis TCP protocol on --port (connect with "
        "nanonis://127.0.0.1:PORT; docs/instruments.md). Stops cleanly on SIGINT/SIGTERM.",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="Serve on a new pseudo-terminal.")
    where.add_argument(
        "--port", type=int, default=None, help="Serve on 127.0.0.1:PORT (default 5025)."
    )
    p.add_argument(
        "--scenario",
        default=None,
        help="Scenario TOML file or built-in name from config/scenarios "
        f"(default: {DEFAULT_SCENARIO}).",
    )
    p.add_argument(
        "--speed",
        type=_speed,
        default=1.0,
        help="Virtual seconds per wall second (1 = real time; 1000 runs 8 h in about 29 s).",
    )
    p.add_argument("--seed", type=int, default=None, help="Override the scenario's seed.")
    p.add_argument(
        "--protocol",
        choices=("line", "nanonis"),
        default="line",
        help="line: the protocol of docs/protocol.md (pty or TCP); nanonis: the Nanonis TCP "
        "protocol (TCP only, no --faults).",
    )
    p.add_argument(
        "--faults",
        type=float,
        default=0.0,
        metavar="RATE",
        help="Perturb this fraction of replies at random (corrupt, truncate, drop, delay, "
        "stale, disconnect): a faulty line for soak tests (default 0).",
    )
    p.set_defaults(handler=_serve)


def _serve(args: argparse.Namespace) -> int:
    import asyncio

    from afmdrift.drivers.sim import SimulatedAFM

    sim = SimulatedAFM.from_scenario(_scenario(args.scenario), seed=args.seed)
    port = None if args.pty else (5025 if args.port is None else args.port)
    if port is not None and not 0 <= port <= 65535:
        from afmdrift.errors import ConfigError

        raise ConfigError(f"--port {port}: must be in 0..65535")
    if not 0.0 <= args.faults <= 1.0:
        from afmdrift.errors import ConfigError

        raise ConfigError(f"--faults {args.faults}: must be a fraction in [0, 1]")
    if args.protocol == "nanonis":
        from afmdrift.errors import ConfigError

        if port is None or args.faults:
            raise ConfigError("--protocol nanonis serves TCP only (--port N), without --faults")
        asyncio.run(_serve_until_signal(sim, port=port, speed=args.speed, protocol="nanonis"))
        return 0
    asyncio.run(_serve_until_signal(sim, port=port, speed=args.speed, faults=args.faults))
    return 0


def _scenario(name: str | None) -> Any:
    from afmdrift.drivers.sim import SCENARIO_DIR, Scenario

    if name is not None:
        return name
    default = SCENARIO_DIR / f"{DEFAULT_SCENARIO}.toml"
    return default if default.is_file() else Scenario()


async def _serve_until_signal(
    sim: Any, *, port: int | None, speed: float, faults: float = 0.0, protocol: str = "line"
) -> None:
    """Serve ``sim`` over ``protocol`` (TCP on ``port``, or a pseudo-terminal
    for the line protocol) until SIGINT or SIGTERM; print the address."""
    import asyncio
    import signal

    from afmdrift.drivers.sim._nanonis_server import NanonisSimServer
    from afmdrift.drivers.sim._server import ServerFaults, SimulatorServer
    from afmdrift.errors import ConfigError

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    server: NanonisSimServer | SimulatorServer
    if protocol == "nanonis":
        server = NanonisSimServer(sim, speed=speed)
    else:
        server = SimulatorServer(sim, speed=speed, faults=ServerFaults(seed=1, random_rate=faults))
    try:
        async with server:
            if port is None and isinstance(server, SimulatorServer):
                path = await server.start_pty()
                where, url = f"the pseudo-terminal {path}", path
                print(path, flush=True)
            else:
                assert port is not None
                try:
                    bound = await server.start_tcp(port)
                except OSError as err:
                    raise ConfigError(
                        f"--port {port}: cannot listen on 127.0.0.1:{port}: {err.strerror}"
                    ) from None
                scheme = "nanonis" if protocol == "nanonis" else "socket"
                where, url = f"127.0.0.1:{bound}", f"{scheme}://127.0.0.1:{bound}"
                # the first line on stdout is the port alone: scripts and tests read it
                print(bound, flush=True)
            print(_serving_text(sim, protocol=protocol, where=where, url=url, speed=speed),
                  file=sys.stderr, flush=True)  # fmt: skip
            await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def _serving_text(sim: Any, *, protocol: str, where: str, url: str, speed: float) -> str:
    """What ``sim serve`` serves, for the person who started it."""
    name = "the Nanonis TCP protocol" if protocol == "nanonis" else "the line protocol"
    return (
        f"afmdrift sim serve: the simulated AFM of scenario {sim.scenario.name!r} "
        f"(seed {sim.seed}) over {name} on {where}, at {speed:g}x real time; "
        f"connect with --instrument {url}; SIGINT (Ctrl-C) or SIGTERM stops it"
    )

"""``afmdrift dashboard``: a live page for a running daemon or a finished run."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "dashboard",
        help="Serve a live page of the drift: follow a daemon, or open a finished run.",
        description="Serve a page on 127.0.0.1 that follows a running daemon through its "
        "ZeroMQ topics and its run store (read-only), or shows a finished run directory. "
        "Without --run-dir it follows the configured daemon (service.pub_endpoint and "
        "service.run_dir); with --run-dir alone the run is shown as finished; add --pub "
        "(or --live for the configured endpoint) to follow its daemon. Following a daemon, "
        "it waits for the run directory and its store to appear (the daemon creates them "
        "when it starts). See docs/dashboard.md.",
    )
    p.add_argument(
        "--config", default=None, help="TOML configuration (default: config/default.toml)"
    )
    p.add_argument(
        "--run-dir",
        default=None,
        help="run directory to read (read-only); with --pub or --live, waited for until "
        "the daemon creates it",
    )
    p.add_argument("--pub", default=None, help="the daemon's PUB endpoint to follow")
    p.add_argument(
        "--control",
        default=None,
        help="the daemon's control endpoint, for the page's 'Add to model' (default: "
        "service.control_endpoint when following the configured daemon)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="with --run-dir: also follow the configured daemon (service.pub_endpoint)",
    )
    p.add_argument(
        "--session",
        default=None,
        help="the session the run came from: true drift (truth.csv) and frame images",
    )
    p.add_argument(
        "--diagnosis",
        default=None,
        help="diagnose JSON result to show (default: RUN_DIR/diagnosis.json)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8050, help="port (default 8050; 0: any free)")
    p.add_argument(
        "--token-file",
        default=None,
        help="file holding the access token (required reading for a non-loopback --host; "
        "without it one is generated and printed). Give the daemon's RUN_DIR/control.token "
        "to let the page add a diagnosed term to the daemon's model (add_term): the page "
        "then needs that token to open",
    )
    p.add_argument(
        "--wait-s",
        type=float,
        default=10.0,
        help="with --pub and no run directory: give up when the daemon sends nothing for "
        "this long at start (default 10 s)",
    )
    p.add_argument(
        "--max-frames", type=int, default=5000, help="frames kept on the page (default 5000)"
    )
    p.set_defaults(handler=_dashboard)


def _dashboard(args: argparse.Namespace) -> int:
    import asyncio
    import secrets
    from pathlib import Path

    from afmdrift.config import host_is_loopback, load_config
    from afmdrift.dashboard import DashboardError

    if args.max_frames < 10:
        raise DashboardError(f"--max-frames must be at least 10, got {args.max_frames}")
    config = load_config(args.config)
    if args.wait_s <= 0:
        raise DashboardError(f"--wait-s must be > 0, got {args.wait_s}")
    run_dir = args.run_dir
    pub = args.pub
    control_endpoint = args.control
    if run_dir is None and pub is None:
        run_dir, pub = config.service.run_dir, config.service.pub_endpoint
        control_endpoint = control_endpoint or config.service.control_endpoint
    elif args.live and pub is None:
        pub = config.service.pub_endpoint
        control_endpoint = control_endpoint or config.service.control_endpoint
    # Following a daemon: its run directory and store appear when it starts,
    # which may be after the dashboard (a service unit, a script starting both).
    wait_for_store = run_dir is not None and pub is not None
    token = control_token = None
    if args.token_file is not None:
        try:
            token = Path(args.token_file).read_text(encoding="utf-8").strip()
        except OSError as err:
            raise DashboardError(f"--token-file {args.token_file}: {err.strerror}") from None
        if len(token) < 16:
            raise DashboardError(
                f"--token-file {args.token_file}: token shorter than 16 characters"
            )
        control_token = token
    elif not host_is_loopback(args.host):
        token = secrets.token_urlsafe(24)
    return asyncio.run(
        _serve(
            args,
            config=config,
            run_dir=run_dir,
            pub=pub,
            token=token,
            control=(control_endpoint, control_token),
            wait_for_store=wait_for_store,
        )
    )


async def _serve(
    args: argparse.Namespace,
    *,
    config: Any,
    run_dir: str | None,
    pub: str | None,
    token: str | None,
    control: tuple[str | None, str | None],
    wait_for_store: bool,
) -> int:
    import asyncio
    import signal

    from afmdrift.dashboard import Dashboard, load_session

    truth = None
    session = None
    if args.session is not None:
        session, truth = load_session(args.session)
    dash = Dashboard(
        run_dir=run_dir,
        pub_endpoint=pub,
        config=config,
        host=args.host,
        port=args.port,
        token=token,
        control_endpoint=control[0],
        control_token=control[1],
        truth=truth,
        session=session,
        diagnosis_path=args.diagnosis,
        max_frames=args.max_frames,
        wait_for_store=wait_for_store,
        first_message_timeout_s=args.wait_s,
    )
    main = asyncio.current_task()
    assert main is not None
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, main.cancel)
    try:
        async with dash:
            what = f"following {pub}" if pub else "finished run"
            where = f"run directory {run_dir}" if run_dir else "no run directory"
            print(f"afmdrift dashboard: {dash.url} ({what}; {where})", flush=True)
            if dash.waiting_for_store is not None:
                print(f"afmdrift dashboard: {dash.waiting_for_store}", flush=True)
            await dash.serve_forever()
    except asyncio.CancelledError:
        return 0
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    return 0

"""``afmdrift demo``: the whole system on a simulated AFM, in under a minute.

The simulated AFM (:mod:`afmdrift.drivers.sim`) is served over its instrument
protocol on a pseudo-terminal (or loopback TCP) on an accelerated clock; the
drift service (:class:`afmdrift.service.DriftService`) connects to it with the
production driver, measures every frame, predicts, publishes the offset d(t)
over ZeroMQ and records the run; a subscriber (:mod:`afmdrift.client`) prints
each frame as it arrives next to the simulator's true drift and samples the
published offset stream. The summary names the run directory and gives the
frames, the drift, the prediction error and the offset error against truth.

The live dashboard (:mod:`afmdrift.dashboard`) follows the service from the
start, with the simulator's true drift; its address is printed first and ends
the summary (``--hold`` keeps it serving the finished run until Ctrl-C).

Everything runs in one process and one event loop; nothing leaves 127.0.0.1.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path
from typing import Any

#: Pixel size of the simulated frames (nm).
PIXEL_NM = 2.0
#: Frame period of the simulated instrument (s), as in Yang et al. (2008).
FRAME_PERIOD_S = 256.0
#: Lines per second of the simulated scanner.
LINE_RATE_HZ = 4.0


def register(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="Run the simulated AFM, the drift service and a subscriber; print a summary.",
        description="Serve the simulated AFM over a pseudo-terminal on an accelerated clock, "
        "run the drift service on it and subscribe to its offsets. Prints each frame's true "
        "and measured cumulative drift and the prediction error, then a summary (frames, "
        "drift, prediction error, offset error against truth) naming the run directory.",
    )
    p.add_argument("--frames", type=int, default=24, help="frames to run (default 24)")
    p.add_argument("--size", type=int, default=256, help="frame edge in px (default 256)")
    p.add_argument("--snr", type=float, default=10.0, help="height SNR (default 10)")
    p.add_argument("--seed", type=int, default=2008, help="random seed (default 2008)")
    p.add_argument(
        "--speed",
        type=float,
        default=256.0,
        help="simulated seconds per wall second (default 256: one frame per second)",
    )
    p.add_argument(
        "--transport", choices=("pty", "tcp"), default="pty", help="simulator line (default pty)"
    )
    p.add_argument("--predictor", default=None, help="predictor (default: [model] predictor)")
    p.add_argument(
        "--config", default=None, help="TOML configuration (default: config/default.toml)"
    )
    p.add_argument("--run-dir", default=None, help="run directory (default: runs/demo-<UTC time>)")
    p.add_argument(
        "--dashboard-port",
        type=int,
        default=0,
        help="port of the live dashboard on 127.0.0.1 (default 0: any free port)",
    )
    p.add_argument("--no-dashboard", action="store_true", help="do not start the dashboard")
    p.add_argument(
        "--hold",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="after the summary, keep the dashboard serving the finished run until Ctrl-C "
        "(default: when run in a terminal; never under CI or a script)",
    )
    p.set_defaults(handler=_demo)


def drift_scenario(*, size_px: int, seed: int, noise_nm: float) -> Any:
    """The demo's scenario: gold colloids on mica, power-on settling, thermal and
    random-walk drift (see docs/physics.md), ``size_px``² frames at 2 nm/px."""
    from afmdrift.drivers.sim import parse_scenario

    return parse_scenario(
        {
            "name": "demo",
            "seed": seed,
            "duration_s": 30 * 86400.0,
            "scan": {
                "pixels": [size_px, size_px],
                "size_nm": [PIXEL_NM * size_px, PIXEL_NM * size_px],
                "line_rate_hz": LINE_RATE_HZ,
                "frame_period_s": max(FRAME_PERIOD_S, size_px / LINE_RATE_HZ),
                "directions": "up",
            },
            "sample": {
                "kind": "gold_on_mica",
                "grid_nm": 1.0,
                "map_px": 2048,
                "roughness_nm": 0.5,
                "gold": {"density_per_um2": 250.0},
            },
            "physics": {
                "warmup": {"enabled": True, "amplitude_nm": [90.0, -60.0], "tau_s": 5000.0},
                "random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": [0.01, 0.01]},
            },
            "artefacts": {"noise_nm": noise_nm},
        },
        source="demo",
    )


def _demo(args: argparse.Namespace) -> int:
    import asyncio

    from afmdrift.errors import InputError

    if args.frames < 2:
        raise InputError(f"--frames must be at least 2, got {args.frames}")
    if not 64 <= args.size <= 1024:
        raise InputError(f"--size must be between 64 and 1024 px, got {args.size}")
    if not args.snr > 0:
        raise InputError(f"--snr must be > 0, got {args.snr}")
    if not 1.0 <= args.speed <= 5000.0:
        raise InputError(f"--speed must be between 1 and 5000, got {args.speed}")
    if not 0 <= args.dashboard_port <= 65535:
        raise InputError(f"--dashboard-port must be between 0 and 65535, got {args.dashboard_port}")
    return asyncio.run(_run_demo(args))


async def _run_demo(args: argparse.Namespace) -> int:
    import asyncio
    import time

    import zmq.asyncio

    from afmdrift.client import Subscriber
    from afmdrift.drivers import NanoScopeDriver
    from afmdrift.drivers.sim._server import SimulatorServer
    from afmdrift.service import DriftService

    sim = _demo_simulator(args)
    run_dir = Path(args.run_dir or f"runs/demo-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}")
    config = _demo_config(args, run_dir)
    print(
        f"afmdrift demo: simulated AFM ({args.size}x{args.size} px at {PIXEL_NM:g} nm/px, gold "
        f"colloids, SNR {args.snr:g}, one frame per {FRAME_PERIOD_S:g} s) served over a "
        f"{'pseudo-terminal' if args.transport == 'pty' else 'loopback TCP'} at {args.speed:g}x; "
        f"drift service with predictor {config.model.predictor!r}; subscriber on ZeroMQ"
    )
    ctx = zmq.asyncio.Context()
    dashboard = None
    tally = _Tally(sim=sim, rows=args.size)
    started = time.monotonic()
    budget_s = 60.0 + 3.0 * args.frames * FRAME_PERIOD_S / args.speed
    try:
        async with SimulatorServer(sim, speed=args.speed) as server:
            if args.transport == "pty":
                url = await server.start_pty()
            else:
                url = f"socket://127.0.0.1:{await server.start_tcp(0)}"
            service = DriftService(
                config=config, instrument=NanoScopeDriver(url), ctx=ctx, config_path=args.config
            )
            task = asyncio.create_task(service.run(), name="afmdrift-demo-service")
            try:
                await asyncio.wait_for(service.ready.wait(), 30.0)
                print(f"simulator on {url}; service publishing on {service.pub_endpoint}")
                if not args.no_dashboard:
                    dashboard = await _start_dashboard(args, config, run_dir, service, sim)
                    print(f"dashboard: {dashboard.url}", flush=True)
                print(_HEADER)
                sub = Subscriber(service.pub_endpoint, topics=("frame", "offset"), ctx=ctx)
                try:
                    async with asyncio.timeout(budget_s):
                        while tally.frames_seen < args.frames:
                            tally.take(await sub.recv())
                finally:
                    sub.close()
            finally:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
    except BaseException:
        if dashboard is not None:
            await dashboard.close()
        raise
    finally:
        ctx.term()
    try:
        return await _summarise(
            args,
            config,
            run_dir,
            started=started,
            frames_seen=tally.frames_seen,
            errors=tally.errors,
            rejected=tally.rejected,
            pred_errors=tally.pred_errors,
            offset_errors=tally.offset_errors,
            ref_truth=tally.ref_truth,
            dashboard=dashboard,
        )
    finally:
        if dashboard is not None:
            await dashboard.close()


_HEADER = (
    f"{'frame':>5} {'t_s':>6} {'true_x_nm':>10} {'true_y_nm':>10} {'meas_x_nm':>10} "
    f"{'meas_y_nm':>10} {'err_nm':>7} {'blocks':>7} {'pred_err_nm':>11}"
)


def _demo_simulator(args: argparse.Namespace) -> Any:
    """The demo's simulated AFM, its detector noise set from ``--snr``: the
    sample's height spread over one noiseless frame, divided by the SNR."""
    import numpy as np

    from afmdrift.drivers.sim import SimulatedAFM

    probe = SimulatedAFM(drift_scenario(size_px=args.size, seed=args.seed, noise_nm=0.0))
    first = probe.advance_to(max(FRAME_PERIOD_S, args.size / LINE_RATE_HZ) + 1.0)[0]
    noise_nm = float(np.std(first.heights_nm)) / args.snr
    return SimulatedAFM(drift_scenario(size_px=args.size, seed=args.seed, noise_nm=noise_nm))


def _demo_config(args: argparse.Namespace, run_dir: Path) -> Any:
    """``--config`` (or the default) with the demo's run directory, free loopback
    ports, fast polling and ``--predictor``."""
    from afmdrift.config import load_config

    base = load_config(args.config)
    model = base.model
    if args.predictor is not None:
        model = model.model_copy(update={"predictor": args.predictor})
    service = base.service.model_copy(
        update={
            "run_dir": str(run_dir),
            "pub_endpoint": "tcp://127.0.0.1:*",
            "control_endpoint": "tcp://127.0.0.1:*",
            "frame_poll_interval_s": 0.05,
            "clock_sync_interval_s": 0.1,
            "channel_poll_interval_s": 0.5,
            "event_poll_interval_s": 0.5,
            "heartbeat_interval_s": 0.5,
        }
    )
    return base.model_copy(update={"model": model, "service": service})


class _Tally:
    """What the demo's subscriber saw, against the simulator's truth; prints a
    line per frame."""

    def __init__(self, *, sim: Any, rows: int) -> None:
        self.sim = sim
        self.rows = rows
        self.errors: list[float] = []
        self.rejected = 0
        self.pred_errors: list[float] = []
        self.offset_errors: list[float] = []
        self.ref_truth: Any = None
        self.frames_seen = 0

    def truth(self, t_mid_s: float) -> Any:
        """Mean true drift over the scan lines of the frame centred at ``t_mid_s``."""
        import numpy as np

        from afmdrift.model import truth_frame_mean
        from afmdrift.records import Frame, ScanDirection

        scan_s = self.rows / LINE_RATE_HZ
        frame = Frame(
            index=0,
            heights_nm=np.zeros((self.rows, 1)),
            pixel_size_nm=(PIXEL_NM, PIXEL_NM),
            t_start_s=t_mid_s - scan_s / 2,
            t_end_s=t_mid_s + scan_s / 2,
            direction=ScanDirection.UP,
        )
        t = np.linspace(frame.t_start_s, frame.t_end_s, 256)
        x, y = self.sim.truth_at(t)
        return truth_frame_mean(frame, t, np.stack([x, y], axis=1))

    def take(self, msg: Any) -> None:
        """Score one ``offset`` or ``frame`` message."""
        from afmdrift.wire import FrameMsg, OffsetMsg

        if isinstance(msg, OffsetMsg):
            if msg.valid and self.ref_truth is not None:
                x, y = self.sim.truth_at(msg.t_s)
                self.offset_errors.append(
                    math.hypot(
                        msg.x_nm - (x - self.ref_truth[0]), msg.y_nm - (y - self.ref_truth[1])
                    )
                )
            return
        if isinstance(msg, FrameMsg):
            self._frame(msg)

    def _frame(self, msg: Any) -> None:
        self.frames_seen += 1
        if self.ref_truth is None:
            self.ref_truth = self.truth(msg.t_s)
        true = self.truth(msg.t_s) - self.ref_truth
        blocks = f"{msg.valid_blocks}/{msg.total_blocks}"
        pred = "-" if msg.pred_error_nm is None else f"{msg.pred_error_nm:.3f}"
        where = f"{msg.frame:5d} {msg.t_s:6.0f} {true[0]:10.2f} {true[1]:10.2f}"
        if msg.reason == "reference":
            print(f"{where} {'reference':>21}")
            return
        if msg.x_nm is None or msg.y_nm is None:
            self.rejected += 1
            print(
                f"{where} {'-':>10} {'-':>10} {'-':>7} {blocks:>7} {pred:>11}  "
                f"rejected: {msg.reason}"
            )
            return
        err = math.hypot(msg.x_nm - true[0], msg.y_nm - true[1])
        self.errors.append(err)
        if msg.pred_error_nm is not None:
            self.pred_errors.append(msg.pred_error_nm)
        print(f"{where} {msg.x_nm:10.2f} {msg.y_nm:10.2f} {err:7.3f} {blocks:>7} {pred:>11}")


async def _start_dashboard(
    args: argparse.Namespace, config: Any, run_dir: Path, service: Any, sim: Any
) -> Any:
    """The live dashboard on the demo's service, with the simulator's true drift."""
    import numpy as np

    from afmdrift.dashboard import Dashboard, FunctionTruth

    def truth_nm(t_s: Any) -> Any:
        x, y = sim.truth_at(t_s)
        return np.stack([np.asarray(x), np.asarray(y)], axis=-1)

    dashboard = Dashboard(
        run_dir=run_dir,
        pub_endpoint=service.pub_endpoint,
        config=config,
        port=args.dashboard_port,
        truth=FunctionTruth(truth_nm, label="the demo's simulator (true drift)"),
        store_poll_s=0.5,
    )
    await dashboard.start()
    return dashboard


async def _summarise(
    args: argparse.Namespace,
    config: Any,
    run_dir: Path,
    *,
    started: float,
    frames_seen: int,
    errors: list[float],
    rejected: int,
    pred_errors: list[float],
    offset_errors: list[float],
    ref_truth: Any,
    dashboard: Any,
) -> int:
    """Print the summary (ending with the dashboard's address) and, with ``--hold``,
    keep the dashboard serving until SIGINT/SIGTERM."""
    import asyncio
    import signal
    import time

    from afmdrift.runs import RunStore

    with RunStore(run_dir) as store:
        csv_path = store.write_measurements_csv()
        records = store.frames()
    wall_s = time.monotonic() - started
    last = records[-1] if records else None
    rms = math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.nan
    print(
        f"RMS error of cumulative drift: {rms:.3f} nm ({rms / PIXEL_NM:.4f} px) over "
        f"{len(errors)} measured frames; {rejected} rejected"
    )
    print(f"summary after {wall_s:.1f} s of wall time:")
    print(f"  frames: {frames_seen} received by the subscriber, {len(records)} in the run store")
    if last is not None and ref_truth is not None:
        span_s = last.t_mid_s - records[0].t_mid_s
        print(
            f"  drift: measured ({last.x_nm:.1f}, {last.y_nm:.1f}) nm over {span_s / 3600:.2f} h "
            f"of instrument time ({math.hypot(last.x_nm, last.y_nm) / max(span_s, 1e-9):.4f} "
            "nm/s on average)"
        )
    if pred_errors:
        print(
            f"  prediction error (made before each frame arrived): mean "
            f"{sum(pred_errors) / len(pred_errors):.2f} nm, max {max(pred_errors):.2f} nm over "
            f"{len(pred_errors)} frames (Yang et al. 2008: mean 1.62 nm, peak 6.88 nm)"
        )
    if offset_errors:
        print(
            f"  offset error against truth: mean {sum(offset_errors) / len(offset_errors):.2f} nm,"
            f" max {max(offset_errors):.2f} nm over {len(offset_errors)} published samples "
            f"({config.service.offset_rate_hz:g} Hz)"
        )
    print(f"  run directory: {run_dir} (run.sqlite, {csv_path.name})")
    if dashboard is None:
        return 0
    hold = args.hold if args.hold is not None else sys.stdin.isatty() and sys.stdout.isatty()
    if not hold:
        print(
            f"  dashboard: {dashboard.url} (stops with the demo; "
            f"afmdrift dashboard --run-dir {run_dir} shows the run again)"
        )
        return 0
    print(f"  dashboard: {dashboard.url} (serving the finished run; Ctrl-C to stop)", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    return 0

"""``afmdrift watch``: print the live offset and the rolling prediction error."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "watch",
        help="Print live offsets and the rolling prediction error of a running service.",
        description="Subscribe to a running `afmdrift run` and print one line per interval: "
        "the published offset d(t), its validity, the state and flags, and the rolling "
        "prediction error. Frame measurements are printed as they arrive.",
    )
    p.add_argument("--config", default=None, help="configuration naming the endpoint")
    p.add_argument("--endpoint", default=None, help="PUB endpoint (overrides the config)")
    p.add_argument("--interval-s", type=float, default=1.0, help="seconds between lines")
    p.add_argument("--duration-s", type=float, default=None, help="stop after this many seconds")
    p.set_defaults(handler=_watch)


def _watch(args: argparse.Namespace) -> int:
    import asyncio

    from afmdrift.client._watch import watch
    from afmdrift.config import load_config

    endpoint = args.endpoint or load_config(args.config).service.pub_endpoint
    try:
        asyncio.run(watch(endpoint, interval_s=args.interval_s, duration_s=args.duration_s))
    except KeyboardInterrupt:
        return 130
    return 0

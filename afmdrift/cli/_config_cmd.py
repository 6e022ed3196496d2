"""``afmdrift config check FILE``: validate a configuration file."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("config", help="Work with configuration files.")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION")
    csub.required = True
    check = csub.add_parser(
        "check",
        help="Validate a TOML configuration file.",
        description="Validate FILE exactly as `afmdrift run` would (keys, types and ranges, "
        "then the predictor, its effect terms and plugins, CURVE keys and the instrument "
        "URL); print each problem with its key, value and allowed range. Plugins are "
        "imported: configuration files are trusted input.",
    )
    check.add_argument("file", help="TOML configuration file")
    check.add_argument(
        "--instrument", default=None, help="instrument URL overriding [driver], as for `run`"
    )
    check.set_defaults(handler=_check)
    show = csub.add_parser("show", help="Print the effective configuration as JSON.")
    show.add_argument("file", nargs="?", help="TOML file (default: config/default.toml)")
    show.set_defaults(handler=_show)


def _check(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.service import check_config

    check_config(load_config(args.file), instrument_url=args.instrument)
    print(f"{args.file}: OK")
    return 0


def _show(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config

    print(load_config(args.file).model_dump_json(indent=2))
    return 0

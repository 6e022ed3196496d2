"""``afmdrift control``: every control command of a running daemon, from the shell.

One subcommand per command of the control socket (``docs/wire.md``):
``status``, ``model``, ``pause``, ``resume``, ``reset-reference``,
``reload-model [PATH]``, ``add-term TERM``, ``remove-term TERM``,
``diagnose`` (start a live diagnosis; its result comes on topic
``diagnosis``). The
endpoint and the token file default to the configuration's
(``service.control_endpoint``, ``service.control_token_file`` or
``RUN_DIR/control.token``). The answer is one line, or the reply as JSON with
``--json``. Exit status: 0 when the daemon did it, 1 when it refused (the
reason on standard error), 2 for an error (no daemon answering, bad
arguments, an unreadable token file).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from afmdrift.wire import ControlReply

#: Subcommand → (wire command, help, argument: (name, help) or None).
_COMMANDS: dict[str, tuple[str, str, tuple[str, str] | None]] = {
    "status": ("status", "The daemon's status (state, frames, error, terms, flags).", None),
    "model": ("model", "The current model message (the published d(t) curve).", None),
    "pause": ("pause", "Stop feeding the model; offsets are published invalid.", None),
    "resume": ("resume", "Feed the model and publish valid offsets again.", None),
    "reset-reference": (
        "reset_reference",
        "Make the next frame the registration reference (the drift position goes on).",
        None,
    ),
    "reload-model": (
        "reload_model",
        "Re-read [model] from PATH (default: the daemon's configuration file) and refit.",
        ("path", "configuration file the daemon may read (docs/service.md)"),
    ),
    "add-term": (
        "add_term",
        "Add an effect term to the running physics model and refit on the run's history.",
        ("term", "a term name or spec, as in [model.physics] terms (docs/model.md)"),
    ),
    "remove-term": (
        "remove_term",
        "Take an effect term out of the running physics model and refit.",
        ("term", "a term of the model (see `afmdrift control status`)"),
    ),
    "diagnose": (
        "diagnose",
        "Diagnose the run now, beside the daemon (the result on topic diagnosis and in "
        "RUN_DIR/diagnoses.jsonl; not started while one runs).",
        None,
    ),
}


def register(sub: Any) -> None:
    p = sub.add_parser(
        "control",
        help="Send a control command to a running service (status, pause, add-term, ...).",
        description="Send one command to the control socket of a running `afmdrift run` and "
        "print its answer on one line (--json: the whole reply). Exit status 0: done; "
        "1: refused by the daemon (the reason on standard error); 2: an error (no daemon "
        "answering, bad arguments, an unreadable token file).",
    )
    csub = p.add_subparsers(dest="control_command", metavar="COMMAND")
    csub.required = True
    for name, (cmd, text, arg) in _COMMANDS.items():
        c = csub.add_parser(name, help=text, description=text)
        if arg is not None:
            arg_name, arg_help = arg
            nargs = "?" if cmd == "reload_model" else None
            c.add_argument(arg_name, nargs=nargs, help=arg_help)
        c.add_argument("--config", default=None, help="configuration naming the endpoint")
        c.add_argument(
            "--endpoint", default=None, help="control endpoint (overrides the configuration)"
        )
        c.add_argument(
            "--token-file",
            default=None,
            help="the daemon's token file (default: from the configuration)",
        )
        c.add_argument(
            "--timeout-s", type=float, default=10.0, help="seconds to wait for the reply"
        )
        c.add_argument("--json", action="store_true", help="print the reply as JSON")
        c.set_defaults(handler=_control, wire_cmd=cmd)


def _control(args: argparse.Namespace) -> int:
    import asyncio
    import sys

    from afmdrift.client import ControlRefusedError, control
    from afmdrift.config import load_config
    from afmdrift.errors import ConfigError
    from afmdrift.wire import STATE_CHANGING

    svc = load_config(args.config).service
    endpoint = args.endpoint or svc.control_endpoint
    if endpoint.endswith(":*"):
        raise ConfigError(
            f"service.control_endpoint {endpoint!r} has no fixed port (the daemon picks one "
            "when it starts and prints it); give --endpoint"
        )
    cmd: str = args.wire_cmd
    token_file = None
    if cmd in STATE_CHANGING and svc.control_auth:
        token_file = args.token_file or svc.token_path
    elif args.token_file is not None:
        token_file = args.token_file
    try:
        reply = asyncio.run(
            control(
                endpoint,
                cmd,
                config_path=getattr(args, "path", None),
                term=getattr(args, "term", None),
                token_file=token_file,
                timeout_s=args.timeout_s,
            )
        )
    except ControlRefusedError as err:
        if args.json:
            print(err.reply.model_dump_json())
        print(f"afmdrift: {err}", file=sys.stderr)
        return 1
    print(reply.model_dump_json() if args.json else answer_line(cmd, reply))
    return 0


def answer_line(cmd: str, reply: ControlReply) -> str:
    """The one-line answer to ``cmd`` (a successful reply)."""
    st = reply.status
    if cmd == "model":
        m = reply.model
        if m is None:
            return "model: none yet (no frame has fed the model)"
        return f"model: {m.predictor}, after frame {m.frame}, t = {m.t_s:.1f} s"
    if st is None:
        return f"{cmd}: ok"
    terms = "none (not the physics model)" if st.terms is None else ", ".join(st.terms)
    if cmd == "status":
        err = "n/a" if st.rolling_error_nm is None else f"{st.rolling_error_nm:.3g} nm"
        flags = ", ".join(st.flags) or "none"
        return f"{st.state}: {st.frames} frames, error {err}; terms: {terms}; flags: {flags}"
    if cmd in ("add_term", "remove_term", "reload_model"):
        return f"{cmd}: ok; terms: {terms}"
    if cmd == "diagnose":
        if reply.started:
            return "diagnose: started (its result comes on topic diagnosis)"
        return "diagnose: not started, one is running"
    return f"{cmd}: ok ({st.state})"

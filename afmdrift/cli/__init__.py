"""The ``afmdrift`` command.

Each subcommand lives in its own module under :mod:`afmdrift.cli` and exposes
``register(subparsers)``. Modules import heavy dependencies (FFTW, torch) inside
their handlers so that ``--help`` stays fast. A handler returns an exit code.
Deliberate errors (:class:`afmdrift.errors.AfmdriftError`) are printed as one
clear message with exit status 2, never as a traceback; a recording too short
for the result asked (:class:`afmdrift.errors.TooFewFramesError`) exits with
status 1, as a result that could not be had (``measure``'s invalid result).
A closed pipe on standard output (``afmdrift config show | head``) ends every
command quietly, with status 141 (:data:`EXIT_BROKEN_PIPE`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

# One OpenBLAS thread for the command's processes, set before NumPy or SciPy
# load it. The per-frame solves (the drift trajectory's Cholesky factorisation,
# the predictors' least squares) are small; OpenBLAS splits them over its
# threads anyway, and on a loaded machine they wait for each other: a frame's
# trajectory update then took a hundred times longer (benchmarks/RESULTS.md).
# The registration's own threads (FFTW, Numba) do not use BLAS. A value the
# user set is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from afmdrift._version import __version__
from afmdrift.errors import AfmdriftError, TooFewFramesError

__all__ = ["EXIT_BROKEN_PIPE", "build_parser", "main"]

#: Subcommand modules, in the order they appear in ``afmdrift --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "afmdrift.cli._config_cmd",
    "afmdrift.cli._import",
    "afmdrift.cli._measure",
    "afmdrift.cli._batch",
    "afmdrift.cli._sim",
    "afmdrift.cli._evaluate",
    "afmdrift.cli._run",
    "afmdrift.cli._replay",
    "afmdrift.cli._correct",
    "afmdrift.cli._watch",
    "afmdrift.cli._control",
    "afmdrift.cli._diagnose",
    "afmdrift.cli._dashboard",
    "afmdrift.cli._demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="afmdrift",
        description="Measure, predict and compensate AFM drift.",
    )
    parser.add_argument("--version", action="version", version=f"afmdrift {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="More log output (repeatable)."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


#: Exit status when the reader of the output went away (``afmdrift config show
#: | head``): 128 + SIGPIPE, what the shell reports for a command that a closed
#: pipe ended (``yes | head``), so ``set -o pipefail`` sees it as it sees theirs.
EXIT_BROKEN_PIPE = 128 + 13


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command of ``argv``; return its exit status (see the module docstring).

    A closed pipe on standard output ends any command quietly with
    :data:`EXIT_BROKEN_PIPE`.
    """
    try:
        try:
            return _main(argv)
        finally:
            # what is still buffered meets the closed pipe here, not at exit
            sys.stdout.flush()
    except BrokenPipeError:
        # The recipe of the Python documentation (signal, "Note on SIGPIPE"):
        # the rest of the output goes nowhere, so the interpreter's own flush at
        # exit cannot fail again with a traceback.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    try:
        code: int = args.handler(args)
    except TooFewFramesError as err:
        print(f"afmdrift: error: {err}", file=sys.stderr)
        return 1
    except AfmdriftError as err:
        print(f"afmdrift: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return code


def _setup_logging(verbosity: int) -> None:
    import logging

    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

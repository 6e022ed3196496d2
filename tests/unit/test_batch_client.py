"""``afmdrift batch``'s client (the command a user runs) loads the
configuration and ``distributed``, not the numerical stack: the workers
register the frames, and every second the client spends importing is a
second of the archive's wall time on one worker as on many."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

HEAVY = ("numba", "torch", "scipy", "pyfftw", "afmdrift.registration", "afmdrift.runs")


def test_the_batch_command_line_and_client_import_no_numerical_stack() -> None:
    probe = textwrap.dedent(
        f"""
        import json, sys
        from afmdrift.cli import build_parser
        build_parser().parse_args(["batch", "in.npy", "--out", "o"])
        import afmdrift.batch._run, afmdrift.batch._jobs, afmdrift.batch._summary
        print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=60
    )
    assert json.loads(done.stdout) == []

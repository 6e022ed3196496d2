"""Re-analyse an archive of recordings on Dask: ``afmdrift batch``.

Each recording (a stack or movie in any format ``afmdrift measure`` reads, a
series of single-image files, or a session directory) is one task on a Dask
worker, which reads it and writes ``OUT/<stem>/track.jsonl`` (the lines of
``afmdrift measure STACK --json``) and, for ``--task correct``, the
drift-corrected frames; for a session directory, ``--task replay`` and
``--task diagnose`` write what ``afmdrift replay`` and ``afmdrift diagnose``
write (see :mod:`afmdrift.batch._jobs`). ``OUT/summary.csv`` has one row per
recording; a run started again skips what is done. A worker never imports the
daemon nor ZeroMQ.
"""

from afmdrift.batch._jobs import TASKS, Job, Result, run_job
from afmdrift.batch._run import (
    DASK_SETTINGS,
    SCHEDULER_ENV,
    BatchReport,
    Recording,
    dask_environ,
    expand_inputs,
    run_batch,
)
from afmdrift.batch._summary import SUMMARY_COLUMNS

__all__ = [
    "DASK_SETTINGS",
    "SCHEDULER_ENV",
    "SUMMARY_COLUMNS",
    "TASKS",
    "BatchReport",
    "Job",
    "Recording",
    "Result",
    "dask_environ",
    "expand_inputs",
    "run_batch",
    "run_job",
]

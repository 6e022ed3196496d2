"""A batch job keeps frame-sized arrays in the C heap on a worker that a Dask
nanny started with ``MALLOC_TRIM_THRESHOLD_``, and gives the worker its own
heap settings back afterwards.

Each check runs in a fresh interpreter started with the nanny's variable
(glibc reads it once, at start-up) and counts the bytes glibc holds in
``mmap``-ed blocks (``mallinfo2().hblkhd``) while a 2 MiB array (a 512²
float64 frame) is alive."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux")
    or not hasattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), "mallinfo2"),
    reason="glibc 2.33 or later only (mallinfo2)",
)

PROBE = textwrap.dedent(
    """
    import ctypes, ctypes.util, json, threading
    import numpy as np
    from afmdrift.batch._heap import job_heap

    class Info(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in
                    ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                     "fsmblks", "uordblks", "fordblks", "keepcost")]
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.mallinfo2.restype = Info

    def mapped_by_a_frame():
        before = libc.mallinfo2().hblkhd
        frame = np.ones((512, 512))
        grown = libc.mallinfo2().hblkhd - before
        del frame
        return grown

    out = {"before": mapped_by_a_frame()}
    with job_heap():
        out["in_job"] = mapped_by_a_frame()
        entered, leave = threading.Event(), threading.Event()
        def other_job():
            with job_heap():
                entered.set()
                leave.wait()
        t = threading.Thread(target=other_job)
        t.start()
        entered.wait()
    out["other_job_still_running"] = mapped_by_a_frame()
    leave.set()
    t.join()
    out["after"] = mapped_by_a_frame()
    print(json.dumps(out))
    """
)


def probe(trim_threshold: str | None) -> dict[str, int]:
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    if trim_threshold is not None:
        env["MALLOC_TRIM_THRESHOLD_"] = trim_threshold
    done = subprocess.run(
        [sys.executable, "-c", PROBE],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return json.loads(done.stdout)  # type: ignore[no-any-return]


def test_a_job_takes_frames_from_the_heap_and_gives_the_nannys_setting_back() -> None:
    frame = 512 * 512 * 8
    seen = probe("65536")
    # the nanny's setting: every frame-sized array is its own mmap
    assert seen["before"] >= frame
    assert seen["in_job"] == 0
    # a second job on another thread keeps the setting until it leaves too
    assert seen["other_job_still_running"] == 0
    assert seen["after"] >= frame


def test_without_a_nanny_glibcs_dynamic_threshold_stays_on() -> None:
    # glibc's dynamic threshold: the first frame-sized array is mapped, and
    # freeing it raises the threshold, so later frames come from the heap.
    # Setting any threshold would switch that off for good: a job leaves
    # such a process alone, and after it a frame still comes from the heap.
    seen = probe(None)
    assert seen["before"] >= 512 * 512 * 8
    assert seen["in_job"] == 0
    assert seen["after"] == 0

"""Text view of a running service (``afmdrift watch`` and the demo's subscriber)."""

from __future__ import annotations

import asyncio
import sys
import time
from typing import TextIO

import zmq.asyncio

from afmdrift.client import Subscriber
from afmdrift.wire import FrameMsg, OffsetMsg, StatusMsg

__all__ = ["format_frame", "format_offset", "watch"]


def _nm(v: float | None) -> str:
    return "   n/a" if v is None else f"{v:7.2f}"


def format_offset(offset: OffsetMsg | None, status: StatusMsg | None) -> str:
    """One line: time, offset, validity, state, flags, rolling error."""
    if offset is None:
        head = "no offset yet"
    else:
        mark = "valid" if offset.valid else "INVALID"
        head = f"t={offset.t_s:10.1f} s  d=({offset.x_nm:8.2f}, {offset.y_nm:8.2f}) nm  {mark}"
    if status is not None:
        flags = ",".join(status.flags) or "-"
        head += (
            f"  [{status.state}; {flags}]  frames={status.frames}  "
            f"rolling error={_nm(status.rolling_error_nm)} nm"
        )
    return head


def format_frame(frame: FrameMsg) -> str:
    """One line per measured frame."""
    return (
        f"frame {frame.frame:5d}  t={frame.t_s:10.1f} s  "
        f"p=({_nm(frame.x_nm)}, {_nm(frame.y_nm)}) nm"
        f"  sigma={_nm(frame.sigma_nm)}  blocks {frame.valid_blocks}/{frame.total_blocks}"
        f"  pred error={_nm(frame.pred_error_nm)} nm"
        + ("" if frame.fed_model else f"  (not fed: {frame.reason})")
    )


async def watch(
    endpoint: str,
    *,
    interval_s: float = 1.0,
    duration_s: float | None = None,
    out: TextIO = sys.stdout,
    ctx: zmq.asyncio.Context | None = None,
) -> Subscriber:
    """Print offsets every ``interval_s`` and every frame until ``duration_s`` passes."""
    sub = Subscriber(endpoint, ctx=ctx)
    try:
        end = None if duration_s is None else time.monotonic() + duration_s
        next_line = time.monotonic() + interval_s
        while end is None or time.monotonic() < end:
            timeout = max(0.01, next_line - time.monotonic())
            try:
                msg = await sub.recv(timeout_s=timeout)
            except TimeoutError:
                msg = None
            if isinstance(msg, FrameMsg):
                print(format_frame(msg), file=out, flush=True)
            if time.monotonic() >= next_line:
                print(format_offset(sub.offset, sub.status), file=out, flush=True)
                next_line += interval_s
            await asyncio.sleep(0)
    finally:
        sub.close()
    return sub

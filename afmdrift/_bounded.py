"""Reading untrusted bytes with limits: one place for every input boundary.

Files and messages from outside (configuration and session files, control
requests, published messages) are read through these functions, so a FIFO,
``/dev/zero``, a binary or oversized file, or JSON nested a hundred thousand
levels deep gives a :class:`ValueError` naming the problem, never a hang, an
unbounded allocation or a ``RecursionError``. Callers turn it into their own
typed error naming the file or message.
"""

from __future__ import annotations

import json
import stat
from pathlib import Path
from typing import Any

__all__ = ["MAX_JSON_DEPTH", "json_depth", "loads_json", "read_bytes", "read_text"]

#: Deepest nesting of JSON arrays and objects accepted (afmdrift's own need 4).
MAX_JSON_DEPTH = 16


def read_bytes(path: Path, *, max_bytes: int, what: str) -> bytes:
    """The content of a regular file of at most ``max_bytes``.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not a regular file (a FIFO or device is never opened), too large, or
        unreadable; the message names ``what``.
    """
    try:
        st = path.stat()
    except FileNotFoundError:
        raise
    except OSError as err:
        raise ValueError(f"cannot read {what}: {err.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{what} is not a regular file")
    if st.st_size > max_bytes:
        raise ValueError(f"{what} is {st.st_size} bytes; the limit is {max_bytes}")
    try:
        with path.open("rb") as fh:
            raw = fh.read(max_bytes + 1)
    except OSError as err:
        raise ValueError(f"cannot read {what}: {err.strerror}") from None
    if len(raw) > max_bytes:
        raise ValueError(f"{what} is larger than {max_bytes} bytes")
    return raw


def read_text(path: Path, *, max_bytes: int, what: str) -> str:
    """:func:`read_bytes` decoded as UTF-8 (a leading byte-order mark is dropped)."""
    raw = read_bytes(path, max_bytes=max_bytes, what=what)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"{what} is not UTF-8 text (byte {err.start})") from None


def json_depth(data: bytes | str) -> int:
    """Deepest nesting of ``[``/``{`` outside strings (a scan, no recursion)."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    depth = deepest = 0
    in_string = escaped = False
    for b in raw:
        if in_string:
            if escaped:
                escaped = False
            elif b == 0x5C:  # backslash
                escaped = True
            elif b == 0x22:  # quote
                in_string = False
        elif b == 0x22:
            in_string = True
        elif b in (0x5B, 0x7B):
            depth += 1
            deepest = max(deepest, depth)
        elif b in (0x5D, 0x7D):
            depth -= 1
    return deepest


def loads_json(data: bytes | str, *, what: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse JSON no deeper than ``max_depth``, with Python's integer-length limit.

    Raises
    ------
    ValueError
        Not UTF-8, not JSON, nested too deeply, or an integer of more than
        4300 digits; the message names ``what``.
    """
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    if raw.count(b"[") + raw.count(b"{") > max_depth and json_depth(raw) > max_depth:
        raise ValueError(f"{what}: JSON nested deeper than {max_depth} levels")
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{what}: not JSON ({err})") from None
    except (ValueError, RecursionError) as err:  # e.g. an integer of over 4300 digits
        raise ValueError(f"{what}: not usable JSON ({err})") from None

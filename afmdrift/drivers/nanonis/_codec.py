"""The Nanonis TCP protocol: a pure codec (bytes in, bytes out, no I/O).

Facts from the Nanonis TCP protocol documentation (SPECS Zurich), written
down for other implementations in ``docs/protocol.md``:

* Every message is a 40-byte header and a body. The header holds the command
  name (ASCII, padded with zero bytes to 32), the body size (u32), a
  send-response flag (u16; the client sets 1 to get a reply) and 2 zero bytes.
* Bodies are big-endian: ``i`` int32, ``I`` uint32, ``H`` uint16, ``f``
  float32, ``d`` float64. A string is its byte length (int32) then its bytes;
  a 1-D array its element count (int32) then the elements; a string array
  its total size in bytes (int32), its count (int32), then each string with
  its own length prefix; a 2-D float32 array its rows (int32), columns (int32)
  and the data, row after row.
* A reply carries the command's name in its header, the return values, and
  an error block: status (u32, 0 = no error), description length (int32) and
  the description text.

Everything here is a function of bytes or of plain values. Arrays are decoded
with :func:`numpy.frombuffer` on big-endian dtypes, never element by element,
so a 512 × 512 frame costs one copy. Sizes and counts are checked against the
bytes present and against :data:`MAX_BODY_BYTES` before anything is allocated:
a malformed or hostile reply raises :class:`ProtocolError`, it never crashes
or makes the reader wait for bytes that will not come.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.drivers._protocol import InstrumentError, ProtocolError

__all__ = [
    "COMMANDS",
    "HEADER_SIZE",
    "MAX_BODY_BYTES",
    "NAME_SIZE",
    "CommandSpec",
    "Header",
    "NanonisError",
    "decode_body",
    "decode_error_block",
    "decode_header",
    "decode_reply",
    "encode_body",
    "encode_error_block",
    "encode_header",
    "encode_reply",
    "encode_request",
]

HEADER_SIZE = 40
NAME_SIZE = 32
#: Largest body accepted in either direction (a 4096 × 4096 float32 frame fits).
MAX_BODY_BYTES = 80 * 1024 * 1024

#: Scalar type codes and their big-endian struct formats.
_SCALARS: Mapping[str, str] = {"i": ">i", "I": ">I", "H": ">H", "h": ">h", "f": ">f", "d": ">d"}
#: Array element codes and their big-endian numpy dtypes.
_ELEMENTS: Mapping[str, str] = {"i": ">i4", "f": ">f4", "d": ">f8"}

#: Field types: a scalar code, ``str``, ``[i]``/``[f]``/``[d]`` (counted 1-D
#: arrays), ``[str]`` (string array with its byte size and count) or ``2f``.
FieldType = str


class NanonisError(InstrumentError):
    """The controller's reply carried a non-zero error status.

    ``code`` is the status, ``message`` the description, ``command`` the
    command name.
    """


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """Argument and return types of one command, in wire order."""

    args: tuple[FieldType, ...]
    returns: tuple[FieldType, ...]


#: The commands afmdrift uses (driver) and serves (simulator), with their layouts.
COMMANDS: Mapping[str, CommandSpec] = {
    "Scan.Action": CommandSpec(("H", "I"), ()),
    "Scan.StatusGet": CommandSpec((), ("I",)),
    "Scan.WaitEndOfScan": CommandSpec(("i",), ("I", "str")),
    "Scan.FrameSet": CommandSpec(("f", "f", "f", "f", "f"), ()),
    "Scan.FrameGet": CommandSpec((), ("f", "f", "f", "f", "f")),
    "Scan.BufferGet": CommandSpec((), ("[i]", "i", "i")),
    "Scan.SpeedGet": CommandSpec((), ("f", "f", "f", "f", "H", "f")),
    "Scan.FrameDataGrab": CommandSpec(("I", "I"), ("str", "2f", "I")),
    "FolMe.XYPosGet": CommandSpec(("I",), ("d", "d")),
    "FolMe.XYPosSet": CommandSpec(("d", "d", "I"), ()),
    "Piezo.RangeGet": CommandSpec((), ("f", "f", "f")),
    "Piezo.DriftCompSet": CommandSpec(("I", "f", "f", "f", "f"), ()),
    "Piezo.DriftCompGet": CommandSpec((), ("I", "f", "f", "f", "I", "I", "I", "f")),
    "Signals.NamesGet": CommandSpec((), ("[str]",)),
    "Signals.ValsGet": CommandSpec(("[i]", "I"), ("[f]",)),
}


# --------------------------------------------------------------------------- header


@dataclass(frozen=True, slots=True)
class Header:
    """A decoded 40-byte header."""

    name: str
    body_size: int
    response: bool


def encode_header(name: str, body_size: int, *, response: bool = True) -> bytes:
    """The 40-byte header of a message named ``name`` with a body of ``body_size`` bytes."""
    raw = name.encode("ascii")
    if not raw or len(raw) > NAME_SIZE:
        raise ValueError(f"command name must be 1..{NAME_SIZE} ASCII bytes, got {name!r}")
    if not 0 <= body_size <= 0xFFFFFFFF:
        raise ValueError(f"body size {body_size} does not fit a u32")
    return raw.ljust(NAME_SIZE, b"\0") + struct.pack(">IHH", body_size, int(response), 0)


def decode_header(data: bytes, *, max_body_bytes: int = MAX_BODY_BYTES) -> Header:
    """Decode a 40-byte header.

    Raises
    ------
    ProtocolError
        Not 40 bytes, a name that is not printable ASCII, or a body larger
        than ``max_body_bytes``.
    """
    if len(data) != HEADER_SIZE:
        raise ProtocolError(f"a Nanonis header is {HEADER_SIZE} bytes, got {len(data)}")
    raw = data[:NAME_SIZE].rstrip(b"\0")
    if not raw or not all(0x20 < b < 0x7F for b in raw):
        raise ProtocolError(f"malformed command name in header: {data[:NAME_SIZE]!r}")
    body_size, flag, _ = struct.unpack(">IHH", data[NAME_SIZE:])
    if body_size > max_body_bytes:
        raise ProtocolError(
            f"{raw.decode('ascii')}: body of {body_size} bytes exceeds the limit of "
            f"{max_body_bytes} bytes"
        )
    return Header(raw.decode("ascii"), int(body_size), bool(flag))


# --------------------------------------------------------------------------- bodies


def _encode_str(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack(">i", len(raw)) + raw


def _encode_field(kind: FieldType, value: Any) -> bytes:
    if kind in _SCALARS:
        try:
            return struct.pack(_SCALARS[kind], value)
        except struct.error as err:
            raise ValueError(f"value {value!r} does not fit type {kind!r}: {err}") from None
    if kind == "str":
        return _encode_str(str(value))
    if kind == "[str]":
        items = b"".join(_encode_str(s) for s in value)
        return struct.pack(">ii", len(items), len(value)) + items
    if kind in ("[i]", "[f]", "[d]"):
        arr = np.ascontiguousarray(value, dtype=_ELEMENTS[kind[1]])
        if arr.ndim != 1:
            raise ValueError(f"{kind} needs a 1-D array, got shape {arr.shape}")
        return struct.pack(">i", arr.size) + arr.tobytes()
    if kind == "2f":
        arr = np.ascontiguousarray(value, dtype=">f4")
        if arr.ndim != 2:
            raise ValueError(f"2f needs a 2-D array, got shape {arr.shape}")
        return struct.pack(">ii", *arr.shape) + arr.tobytes()
    raise ValueError(f"unknown field type {kind!r}")


def encode_body(types: Sequence[FieldType], values: Sequence[Any]) -> bytes:
    """Encode ``values`` as fields of ``types`` (big-endian)."""
    if len(types) != len(values):
        raise ValueError(f"{len(types)} field type(s) but {len(values)} value(s)")
    return b"".join(_encode_field(k, v) for k, v in zip(types, values, strict=True))


class _Reader:
    """Reads fields from a body, checking every size against the bytes present."""

    def __init__(self, body: bytes, what: str, offset: int = 0) -> None:
        self.body = body
        self.pos = offset
        self.what = what

    def take(self, n: int, field: str) -> int:
        """Reserve ``n`` bytes; returns their start."""
        if n < 0 or self.pos + n > len(self.body):
            raise ProtocolError(
                f"{self.what}: {field} needs {n} byte(s) at offset {self.pos}, "
                f"only {len(self.body) - self.pos} left"
            )
        start = self.pos
        self.pos += n
        return start

    def scalar(self, kind: str, field: str) -> Any:
        fmt = _SCALARS[kind]
        start = self.take(struct.calcsize(fmt), field)
        return struct.unpack_from(fmt, self.body, start)[0]

    def count(self, field: str) -> int:
        n = int(self.scalar("i", field))
        if n < 0:
            raise ProtocolError(f"{self.what}: negative {field} {n}")
        return n

    def text(self, field: str) -> str:
        n = self.count(f"{field} length")
        start = self.take(n, field)
        try:
            return self.body[start : start + n].decode("utf-8")
        except UnicodeDecodeError as err:
            raise ProtocolError(f"{self.what}: {field} is not UTF-8: {err}") from None

    def array(self, dtype: str, n: int, field: str) -> npt.NDArray[Any]:
        size = np.dtype(dtype).itemsize
        if n > (len(self.body) - self.pos) // size:
            raise ProtocolError(
                f"{self.what}: {field} announces {n} element(s), the body holds at most "
                f"{(len(self.body) - self.pos) // size}"
            )
        start = self.take(n * size, field)
        # Native byte order for callers; one vectorised conversion.
        return np.frombuffer(self.body, dtype=dtype, count=n, offset=start).astype(
            np.dtype(dtype).newbyteorder("=")
        )

    def field(self, kind: FieldType, index: int) -> Any:
        name = f"field {index} ({kind})"
        if kind in _SCALARS:
            return self.scalar(kind, name)
        if kind == "str":
            return self.text(name)
        if kind == "[str]":
            size = self.count(f"{name} byte size")
            n = self.count(f"{name} count")
            end = self.pos + size
            if end > len(self.body):
                raise ProtocolError(f"{self.what}: {name} of {size} bytes exceeds the body")
            if n > size // 4:
                raise ProtocolError(f"{self.what}: {name} announces {n} strings in {size} bytes")
            out = [self.text(f"{name} item {k}") for k in range(n)]
            if self.pos != end:
                raise ProtocolError(
                    f"{self.what}: {name} byte size {size} does not match its strings "
                    f"({self.pos - end + size} bytes)"
                )
            return out
        if kind in ("[i]", "[f]", "[d]"):
            n = self.count(f"{name} count")
            return self.array(_ELEMENTS[kind[1]], n, name)
        if kind == "2f":
            rows = self.count(f"{name} rows")
            cols = self.count(f"{name} columns")
            if cols and rows > (len(self.body) - self.pos) // (4 * cols):
                raise ProtocolError(
                    f"{self.what}: {name} of {rows} × {cols} float32 exceeds the body "
                    f"({len(self.body) - self.pos} bytes left)"
                )
            return self.array(">f4", rows * cols, name).reshape(rows, cols)
        raise ValueError(f"unknown field type {kind!r}")


def decode_body(
    types: Sequence[FieldType], body: bytes, *, what: str = "body", offset: int = 0
) -> tuple[tuple[Any, ...], int]:
    """Decode fields of ``types`` from ``body`` at ``offset``.

    Returns the values (scalars as int/float, strings as str, arrays as native
    numpy arrays, string arrays as lists) and the offset after the last field.

    Raises
    ------
    ProtocolError
        A size or count that does not fit the bytes present.
    """
    reader = _Reader(body, what, offset)
    values = tuple(reader.field(kind, k) for k, kind in enumerate(types))
    return values, reader.pos


# --------------------------------------------------------------------------- messages


def encode_request(name: str, *values: Any, response: bool = True) -> bytes:
    """A complete request (header and body) for command ``name`` of :data:`COMMANDS`."""
    spec = _spec(name)
    body = encode_body(spec.args, values)
    return encode_header(name, len(body), response=response) + body


def encode_error_block(status: int = 0, message: str = "") -> bytes:
    """The error block that ends every reply: status (u32), length (i32), text."""
    raw = message.encode("utf-8")
    return struct.pack(">Ii", status, len(raw)) + raw


def decode_error_block(body: bytes, offset: int, *, what: str) -> tuple[int, str]:
    """Decode the error block at ``offset``; it must end the body exactly."""
    reader = _Reader(body, what, offset)
    status = int(reader.scalar("I", "error status"))
    message = reader.text("error description")
    if reader.pos != len(body):
        raise ProtocolError(f"{what}: {len(body) - reader.pos} byte(s) after the error block")
    return status, message


def encode_reply(
    name: str,
    *values: Any,
    error: tuple[int, str] | None = None,
    types: Sequence[str] | None = None,
) -> bytes:
    """A complete reply to ``name``: header, return values and error block.

    With ``values`` empty and an ``error`` given, the reply carries the error
    block alone (the controller's answer to a command it cannot run).
    ``types`` overrides the layout of :data:`COMMANDS` (for unknown commands).
    """
    fields = types if types is not None else _spec(name).returns
    body = encode_body(fields, values) if values else b""
    status, message = error if error is not None else (0, "")
    body += encode_error_block(status, message)
    return encode_header(name, len(body), response=False) + body


def decode_reply(name: str, header: Header, body: bytes) -> tuple[Any, ...]:
    """The return values of a reply to command ``name``.

    Raises
    ------
    ProtocolError
        The reply names another command, or its body does not match the
        command's layout.
    NanonisError
        The error block has a non-zero status.
    """
    spec = _spec(name)
    if header.name != name:
        raise ProtocolError(f"reply to {name} names {header.name!r}")
    if len(body) != header.body_size:
        raise ProtocolError(f"{name}: body of {len(body)} bytes, header says {header.body_size}")
    try:
        values, end = decode_body(spec.returns, body, what=f"reply to {name}")
        status, message = decode_error_block(body, end, what=f"reply to {name}")
    except ProtocolError:
        # An error reply may carry the error block alone.
        try:
            status, message = decode_error_block(body, 0, what=f"reply to {name}")
        except ProtocolError:
            status = 0
        if status == 0:
            raise
        raise NanonisError(status, message, command=name) from None
    if status != 0:
        raise NanonisError(status, message, command=name)
    return values


def _spec(name: str) -> CommandSpec:
    try:
        return COMMANDS[name]
    except KeyError:
        raise ValueError(f"unknown Nanonis command {name!r}") from None

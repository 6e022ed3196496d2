"""The NanoScope/SCPI-style line protocol: a pure codec (bytes in, bytes out, no I/O).

The wire format is documented for other implementations in ``docs/protocol.md``.
In short:

* A command is one ASCII line ``[@TAG ]HEADER[?][ ARG[,ARG...]]`` ended by ``\\n``
  (``\\r\\n`` accepted). ``TAG`` is a decimal sequence number chosen by the client.
* Every reply line starts with the same ``@TAG `` (when the command had one),
  then a reply header: ``OK`` for a set command, ``ERR code,"message"`` for an
  error, or the query's header without ``?`` followed by its values, e.g.
  ``@7 SCAN:SIZE 5000.0,5000.0``. A reply therefore names the command it
  answers, and a client can reject a reply that belongs to another query.
* ``FRAME:DATA?`` answers with a header line ``#FRAME key=value ...`` followed by
  exactly ``bytes`` raw little-endian floats. Its ``crc32`` covers the header
  text before `` crc32=`` and the payload, so a corrupted height, time, shape or
  pixel size is detected, never returned.

Everything here is a function of bytes or of plain values, so it is tested on
its own (including property-based fuzzing of the reply parsers). Transports
move the bytes; :mod:`afmdrift.drivers._nanoscope` and the simulator's server
use this module on either side of the wire.
"""

from __future__ import annotations

import math
import re
import zlib
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from afmdrift.errors import AfmdriftError
from afmdrift.records import ChannelSample, Event, Frame, ScanDirection, event_kind

__all__ = [
    "COMMANDS",
    "ERROR_MESSAGES",
    "LINE_MAX",
    "MAX_FRAME_EDGE",
    "NO_ERROR",
    "ChecksumError",
    "Command",
    "CommandError",
    "CommandSpec",
    "FrameHeader",
    "InstrumentDisconnected",
    "InstrumentError",
    "InstrumentTimeout",
    "OutOfSequenceError",
    "ProtocolError",
    "Reply",
    "args_count_ok",
    "check_header",
    "check_tag",
    "decode_channels",
    "decode_event",
    "decode_frame",
    "decode_frame_header",
    "decode_frame_reply",
    "encode_channels",
    "encode_command",
    "encode_error",
    "encode_event",
    "encode_frame_reply",
    "encode_no_frame",
    "encode_ok",
    "encode_value",
    "format_number",
    "parse_args_floats",
    "parse_command",
    "parse_error_body",
    "parse_floats",
    "parse_int",
    "parse_reply",
]

#: Longest accepted line (command or reply), bytes including the terminator.
LINE_MAX = 4096
#: Largest accepted frame edge (rows or columns) in a ``#FRAME`` header.
MAX_FRAME_EDGE = 8192

#: SCPI-style error codes used by the controller (IEEE 488.2 / SCPI-99 numbering).
ERROR_MESSAGES: Mapping[int, str] = {
    0: "No error",
    -100: "Command error",
    -101: "Invalid character",
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -200: "Execution error",
    -221: "Settings conflict",
    -222: "Data out of range",
    -230: "Data corrupt or stale",
    -350: "Queue overflow",
    -363: "Input buffer overrun",
}
NO_ERROR = (0, "No error")


# --------------------------------------------------------------------------- errors


class ProtocolError(AfmdriftError):
    """Bytes on the line do not follow the protocol (garbled, partial, unexpected)."""


class ChecksumError(ProtocolError):
    """A frame block's CRC-32 does not match its header and payload."""


class OutOfSequenceError(ProtocolError):
    """A reply carries another query's tag or header."""


class CommandError(ProtocolError):
    """A command line cannot be parsed; ``code`` is the SCPI error to report."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


class InstrumentTimeout(AfmdriftError, TimeoutError):  # noqa: N818 (agreed public name)
    """No (complete) reply within the timeout."""


class InstrumentDisconnected(AfmdriftError, ConnectionError):  # noqa: N818 (agreed public name)
    """The connection to the controller is closed or cannot be opened."""


class InstrumentError(AfmdriftError):
    """The controller answered with an error (``ERR code,"message"``)."""

    def __init__(self, code: int, message: str, *, command: str = "") -> None:
        where = f" (command {command!r})" if command else ""
        super().__init__(f"controller error {code}: {message}{where}")
        self.code = code
        self.message = message
        self.command = command


# --------------------------------------------------------------------------- commands


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """What a header accepts: argument counts of its query and set forms.

    ``None`` means the form does not exist. ``query_args`` is the number of
    arguments of the query form (``EVENT:LOG? start`` has one); ``idempotent``
    says whether repeating the command after a lost reply is harmless.
    """

    query_args: int | None
    set_args: int | None
    summary: str
    idempotent: bool = True


#: Every header the controller understands (the simulator's server and the docs use this).
COMMANDS: Mapping[str, CommandSpec] = {
    "*IDN": CommandSpec(0, None, "identify: vendor,model,serial,firmware"),
    "*CLS": CommandSpec(None, 0, "clear the error queue"),
    "SYST:ERR": CommandSpec(0, None, 'pop the oldest error: code,"message"'),
    "SYST:TIME": CommandSpec(0, None, "instrument clock in s"),
    "SCAN:SIZE": CommandSpec(0, 2, "scan size x_nm,y_nm"),
    "SCAN:PIX": CommandSpec(0, 2, "pixels cols,rows"),
    "SCAN:RATE": CommandSpec(0, 1, "line rate in Hz"),
    "SCAN:START": CommandSpec(None, 0, "start continuous scanning"),
    "SCAN:STOP": CommandSpec(None, 0, "stop scanning"),
    "SCAN:STAT": CommandSpec(0, None, "RUN or IDLE"),
    "SCAN:OFFS": CommandSpec(0, 2, "XY scan offset x_nm,y_nm (absolute)"),
    "FRAME:INDEX": CommandSpec(0, None, "index of the last completed frame, -1 if none"),
    "FRAME:TIME": CommandSpec(0, None, "index,t_start_s,t_end_s,dir of the last frame"),
    "FRAME:DATA": CommandSpec(0, None, "last completed frame as a #FRAME block"),
    "CHAN": CommandSpec(0, None, "sensor channels t=..,temperature_c=..,humidity_pct=.."),
    "TIP:MOVE": CommandSpec(None, 2, "move the tip to x_nm,y_nm"),
    "TIP:MAN": CommandSpec(None, 4, "manipulate: push from x0,y0 to x1,y1 (nm)", False),
    "EVENT:COUNT": CommandSpec(0, None, "number of entries in the event log"),
    "EVENT:LOG": CommandSpec(1, None, "event log entries from start: start,count + lines"),
}

_TAG_RE = re.compile(rb"@([0-9]{1,10}) ")
_HEADER_RE = re.compile(r"\*?[A-Z][A-Z0-9]*(?::[A-Z][A-Z0-9]*)*")
_NUMBER_RE = re.compile(r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_INT_RE = re.compile(r"[-+]?[0-9]{1,18}")
_TOKEN_RE = re.compile(r"[A-Za-z0-9_.+\-<>]+")
_NON_PRINTABLE_RE = re.compile(rb"[^\x20-\x7e]")


@dataclass(frozen=True, slots=True)
class Command:
    """One parsed command line.

    Attributes
    ----------
    header : str
        Canonical upper-case header without ``?`` (``"SCAN:SIZE"``).
    query : bool
        The header ended with ``?``.
    args : tuple of str
        Comma-separated arguments, stripped.
    tag : int or None
        The client's sequence tag, echoed at the start of every reply line.
    """

    header: str
    query: bool
    args: tuple[str, ...] = ()
    tag: int | None = None

    @property
    def text(self) -> str:
        """The command as it would be written, without tag and terminator."""
        head = self.header + ("?" if self.query else "")
        return f"{head} {','.join(self.args)}" if self.args else head


def format_number(value: float | int) -> str:
    """Text of a number on the wire: ints as decimals, floats round-trip exactly."""
    if isinstance(value, bool):
        raise ValueError(f"a boolean is not a protocol number: {value!r}")
    if isinstance(value, int | np.integer):
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"protocol numbers must be finite, got {v!r}")
    return repr(v)


def _format_arg(arg: float | int | str) -> str:
    if isinstance(arg, str):
        if not _TOKEN_RE.fullmatch(arg):
            raise ValueError(f"argument {arg!r} is not a plain token")
        return arg
    return format_number(arg)


def _tag_prefix(tag: int | None) -> bytes:
    if tag is None:
        return b""
    if not 0 <= tag < 10**10:
        raise ValueError(f"tag must be in 0..9999999999, got {tag}")
    return b"@%d " % tag


def encode_command(
    header: str, *args: float | int | str, query: bool = False, tag: int | None = None
) -> bytes:
    """Encode one command line.

    >>> encode_command("SCAN:SIZE", 5000.0, 4000.0, tag=3)
    b'@3 SCAN:SIZE 5000.0,4000.0\\n'
    >>> encode_command("EVENT:LOG", 0, query=True)
    b'EVENT:LOG? 0\\n'
    """
    head = header.upper()
    if not _HEADER_RE.fullmatch(head):
        raise ValueError(f"invalid command header {header!r}")
    text = head + ("?" if query else "")
    if args:
        text += " " + ",".join(_format_arg(a) for a in args)
    return _tag_prefix(tag) + text.encode("ascii") + b"\n"


def _strip_terminator(line: bytes) -> bytes:
    if line.endswith(b"\r\n"):
        return line[:-2]
    if line.endswith(b"\n"):
        return line[:-1]
    return line


def _split_tag(line: bytes) -> tuple[int | None, bytes]:
    if not line.startswith(b"@"):
        return None, line
    m = _TAG_RE.match(line)
    if m is None:
        raise ProtocolError(f"malformed tag in {line[:40]!r}")
    return int(m.group(1)), line[m.end() :]


def _ascii_text(raw: bytes, what: str) -> str:
    if len(raw) > LINE_MAX:
        raise ProtocolError(f"{what} longer than {LINE_MAX} bytes")
    if _NON_PRINTABLE_RE.search(raw):
        raise ProtocolError(f"{what} holds non-printable bytes: {raw[:60]!r}")
    return raw.decode("ascii")


def parse_command(line: bytes) -> Command:
    """Parse one command line (the controller's side).

    Raises
    ------
    CommandError
        With the SCPI code to report: -101 bad character, -102 syntax,
        -363 line too long. Unknown headers are *not* checked here (see
        :data:`COMMANDS`).
    """
    if len(line) > LINE_MAX:
        raise CommandError(-363, f"command longer than {LINE_MAX} bytes")
    body = _strip_terminator(line)
    try:
        tag, body = _split_tag(body)
        text = _ascii_text(body, "command")
    except ProtocolError as err:
        raise CommandError(-101, str(err)) from None
    text = text.strip()
    if not text:
        raise CommandError(-102, "empty command")
    head, _, rest = text.partition(" ")
    query = head.endswith("?")
    if query:
        head = head[:-1]
    head = head.upper()
    if not _HEADER_RE.fullmatch(head):
        raise CommandError(-102, f"malformed header {text.partition(' ')[0]!r}")
    rest = rest.strip()
    args = tuple(a.strip() for a in rest.split(",")) if rest else ()
    if any(not a for a in args):
        raise CommandError(-102, f"empty argument in {rest!r}")
    return Command(header=head, query=query, args=args, tag=tag)


# --------------------------------------------------------------------------- replies


@dataclass(frozen=True, slots=True)
class Reply:
    """One reply line: ``[@TAG ]HEADER[ BODY]``.

    ``header`` is ``"OK"``, ``"ERR"``, ``"#FRAME"``, ``"EVENT"`` or a command
    header without ``?``.
    """

    tag: int | None
    header: str
    body: str = ""


def encode_ok(*, tag: int | None = None) -> bytes:
    """Acknowledge a set command."""
    return _tag_prefix(tag) + b"OK\n"


def encode_error(code: int, message: str, *, tag: int | None = None) -> bytes:
    """``ERR code,"message"`` (double quotes in the message become single quotes)."""
    clean = "".join(c if 0x20 <= ord(c) <= 0x7E else "?" for c in message).replace('"', "'")
    return _tag_prefix(tag) + f'ERR {int(code)},"{clean}"\n'.encode("ascii")


def encode_value(header: str, *values: float | int | str, tag: int | None = None) -> bytes:
    """Reply to a query: the query's header (no ``?``) and its values."""
    text = header + (" " + ",".join(_format_arg(v) for v in values) if values else "")
    return _tag_prefix(tag) + text.encode("ascii") + b"\n"


def parse_reply(line: bytes) -> Reply:
    """Parse one reply line (terminator optional).

    Raises
    ------
    ProtocolError
        Non-printable bytes, a malformed tag, or a malformed header.
    """
    body = _strip_terminator(line)
    tag, body = _split_tag(body)
    text = _ascii_text(body, "reply")
    head, _, rest = text.partition(" ")
    if head not in ("OK", "ERR", "#FRAME", "EVENT") and not _HEADER_RE.fullmatch(head):
        raise ProtocolError(f"malformed reply header in {text[:60]!r}")
    return Reply(tag=tag, header=head, body=rest)


def parse_error_body(body: str) -> tuple[int, str]:
    """``-113,"Undefined header"`` → ``(-113, "Undefined header")``."""
    m = re.fullmatch(r'([-+]?[0-9]{1,6}),"([^"]*)"', body)
    if m is None:
        raise ProtocolError(f"malformed error reply {body[:80]!r}")
    return int(m.group(1)), m.group(2)


def _parse_float(text: str, what: str) -> float:
    if not _NUMBER_RE.fullmatch(text):
        raise ProtocolError(f"{what}: not a number: {text[:40]!r}")
    v = float(text)
    if not math.isfinite(v):
        raise ProtocolError(f"{what}: not finite: {text[:40]!r}")
    return v


def parse_int(text: str, what: str = "value") -> int:
    """A decimal integer, or :class:`ProtocolError` naming ``what``."""
    if not _INT_RE.fullmatch(text):
        raise ProtocolError(f"{what}: not an integer: {text[:40]!r}")
    return int(text)


def parse_floats(body: str, n: int, what: str = "value") -> tuple[float, ...]:
    """Exactly ``n`` comma-separated finite numbers."""
    parts = body.split(",") if body else []
    if len(parts) != n:
        raise ProtocolError(f"{what}: expected {n} value(s), got {body[:80]!r}")
    return tuple(_parse_float(p.strip(), what) for p in parts)


# --------------------------------------------------------------------------- channels, events


def encode_channels(sample: ChannelSample, *, tag: int | None = None) -> bytes:
    """``CHAN t=12.5,temperature_c=23.1,humidity_pct=40.0``."""
    items = [f"t={format_number(sample.t_s)}"]
    for name, value in sample.values.items():
        if not re.fullmatch(r"[a-z][a-z0-9_]*", name) or name == "t":
            raise ValueError(f"channel name {name!r} is not a lower-case identifier")
        items.append(f"{name}={format_number(value)}")
    return _tag_prefix(tag) + ("CHAN " + ",".join(items)).encode("ascii") + b"\n"


def decode_channels(body: str) -> ChannelSample:
    """Inverse of :func:`encode_channels` (the body after ``CHAN``)."""
    values: dict[str, float] = {}
    t_s: float | None = None
    for item in body.split(","):
        key, sep, text = item.partition("=")
        if not sep or not re.fullmatch(r"[a-z][a-z0-9_]*", key):
            raise ProtocolError(f"malformed channel item {item[:40]!r}")
        if key in values or (key == "t" and t_s is not None):
            raise ProtocolError(f"channel {key!r} given twice")
        v = _parse_float(text, f"channel {key}")
        if key == "t":
            t_s = v
        else:
            values[key] = v
    if t_s is None:
        raise ProtocolError(f"channel reply without t=: {body[:80]!r}")
    return ChannelSample(t_s=t_s, values=values)


def encode_event(index: int, event: Event, *, tag: int | None = None) -> bytes:
    """``EVENT index,t_s,kind,x_nm,y_nm``: one entry of the event log."""
    return encode_value("EVENT", index, event.t_s, str(event.kind), event.x_nm, event.y_nm, tag=tag)


def decode_event(body: str) -> tuple[int, Event]:
    """Inverse of :func:`encode_event` (the body after ``EVENT``)."""
    parts = body.split(",")
    if len(parts) != 5:
        raise ProtocolError(f"event line needs 5 fields, got {body[:80]!r}")
    index = parse_int(parts[0], "event index")
    try:
        kind = event_kind(parts[2])
    except ValueError as err:
        raise ProtocolError(str(err)) from None
    t_s = _parse_float(parts[1], "event t_s")
    x_nm = _parse_float(parts[3], "event x_nm")
    y_nm = _parse_float(parts[4], "event y_nm")
    return index, Event(t_s=t_s, kind=kind, x_nm=x_nm, y_nm=y_nm)


# --------------------------------------------------------------------------- frame blocks

_DTYPES: dict[str, np.dtype[np.floating]] = {"<f4": np.dtype("<f4"), "<f8": np.dtype("<f8")}
_FRAME_KEYS = ("index", "rows", "cols", "dtype", "bytes", "t_start", "t_end", "dir", "px", "py")


@dataclass(frozen=True, slots=True)
class FrameHeader:
    """Decoded ``#FRAME`` header line: everything but the payload."""

    index: int
    rows: int
    cols: int
    dtype: str
    nbytes: int
    t_start_s: float
    t_end_s: float
    direction: ScanDirection
    pixel_size_nm: tuple[float, float]
    crc32: int
    signed_text: bytes  # header text covered by the CRC (before " crc32=")


def encode_frame_reply(frame: Frame, *, tag: int | None = None) -> bytes:
    """Encode ``frame`` as a ``#FRAME`` header line followed by its payload.

    Heights are sent as little-endian float32 (``<f4``) or float64 (``<f8``),
    whichever the frame holds, row 0 first, C order.
    """
    h = np.asarray(frame.heights_nm)
    if h.ndim != 2:
        raise ValueError(f"frame {frame.index}: heights must be 2-D, got shape {h.shape}")
    code = "<f8" if h.dtype == np.float64 else "<f4"
    payload: bytes = np.ascontiguousarray(h, dtype=_DTYPES[code]).tobytes()
    rows, cols = h.shape
    px, py = frame.pixel_size_nm
    fields = {
        "index": format_number(int(frame.index)),
        "rows": str(rows),
        "cols": str(cols),
        "dtype": code,
        "bytes": str(len(payload)),
        "t_start": format_number(float(frame.t_start_s)),
        "t_end": format_number(float(frame.t_end_s)),
        "dir": ScanDirection(frame.direction).value,
        "px": format_number(float(px)),
        "py": format_number(float(py)),
    }
    signed = ("#FRAME " + " ".join(f"{k}={fields[k]}" for k in _FRAME_KEYS)).encode("ascii")
    crc = zlib.crc32(payload, zlib.crc32(signed))
    return _tag_prefix(tag) + signed + b" crc32=%08x\n" % crc + payload


def encode_no_frame(*, tag: int | None = None) -> bytes:
    """Reply to ``FRAME:DATA?`` before the first frame completed."""
    return _tag_prefix(tag) + b"#FRAME NONE\n"


def decode_frame_header(reply: Reply) -> FrameHeader | None:
    """Decode a ``#FRAME`` reply line; ``None`` for ``#FRAME NONE``.

    Raises
    ------
    ProtocolError
        A missing, repeated, unknown or out-of-range field.
    """
    if reply.header != "#FRAME":
        raise ProtocolError(f"expected a #FRAME header, got {reply.header[:40]!r}")
    if reply.body == "NONE":
        return None
    signed_body, sep, crc_text = reply.body.rpartition(" crc32=")
    if not sep or not re.fullmatch(r"[0-9a-f]{8}", crc_text):
        raise ProtocolError(f"#FRAME header without a valid crc32: {reply.body[:80]!r}")
    fields: dict[str, str] = {}
    for item in signed_body.split(" "):
        key, eq, value = item.partition("=")
        if not eq or key not in _FRAME_KEYS or key in fields:
            raise ProtocolError(f"#FRAME header: bad field {item[:40]!r}")
        fields[key] = value
    if len(fields) != len(_FRAME_KEYS):
        missing = [k for k in _FRAME_KEYS if k not in fields]
        raise ProtocolError(f"#FRAME header: missing field(s) {', '.join(missing)}")
    index = parse_int(fields["index"], "frame index")
    rows = parse_int(fields["rows"], "frame rows")
    cols = parse_int(fields["cols"], "frame cols")
    nbytes = parse_int(fields["bytes"], "frame bytes")
    dtype = fields["dtype"]
    if dtype not in _DTYPES:
        raise ProtocolError(f"#FRAME header: unsupported dtype {dtype[:10]!r} (<f4 or <f8)")
    if index < 0 or not (1 <= rows <= MAX_FRAME_EDGE and 1 <= cols <= MAX_FRAME_EDGE):
        raise ProtocolError(f"#FRAME header: index {index} or shape {rows}x{cols} out of range")
    if nbytes != rows * cols * _DTYPES[dtype].itemsize:
        raise ProtocolError(
            f"#FRAME header: bytes={nbytes} does not match {rows}x{cols} of {dtype}"
        )
    t0 = _parse_float(fields["t_start"], "frame t_start")
    t1 = _parse_float(fields["t_end"], "frame t_end")
    if t1 < t0:
        raise ProtocolError(f"#FRAME header: t_end {t1} before t_start {t0}")
    try:
        direction = ScanDirection(fields["dir"])
    except ValueError:
        raise ProtocolError(f"#FRAME header: bad dir {fields['dir'][:10]!r}") from None
    px = _parse_float(fields["px"], "frame px")
    py = _parse_float(fields["py"], "frame py")
    if px <= 0 or py <= 0:
        raise ProtocolError(f"#FRAME header: pixel size must be positive, got {px}, {py}")
    return FrameHeader(
        index=index,
        rows=rows,
        cols=cols,
        dtype=dtype,
        nbytes=nbytes,
        t_start_s=t0,
        t_end_s=t1,
        direction=direction,
        pixel_size_nm=(px, py),
        crc32=int(crc_text, 16),
        signed_text=("#FRAME " + signed_body).encode("ascii"),
    )


def decode_frame(header: FrameHeader, payload: bytes) -> Frame:
    """Check the payload against ``header`` and build the :class:`Frame`.

    Raises
    ------
    ProtocolError
        The payload has the wrong length.
    ChecksumError
        The CRC-32 over header text and payload does not match.
    """
    if len(payload) != header.nbytes:
        raise ProtocolError(
            f"frame {header.index}: payload of {len(payload)} bytes, header says {header.nbytes}"
        )
    crc = zlib.crc32(payload, zlib.crc32(header.signed_text))
    if crc != header.crc32:
        raise ChecksumError(
            f"frame {header.index}: crc32 {crc:08x} does not match header {header.crc32:08x}"
        )
    heights: npt.NDArray[np.floating] = (
        np.frombuffer(payload, dtype=_DTYPES[header.dtype])
        .reshape(header.rows, header.cols)
        .astype(_DTYPES[header.dtype].newbyteorder("="), copy=True)
    )
    return Frame(
        index=header.index,
        heights_nm=heights,
        pixel_size_nm=header.pixel_size_nm,
        t_start_s=header.t_start_s,
        t_end_s=header.t_end_s,
        direction=header.direction,
    )


def decode_frame_reply(data: bytes, *, tag: int | None = None) -> tuple[Frame | None, int]:
    """Decode a complete ``FRAME:DATA?`` reply held in ``data``.

    Returns the frame (``None`` for ``#FRAME NONE``) and the number of bytes
    consumed. This is the pure counterpart of what the driver does on a live
    line (read a header line, then exactly ``bytes`` bytes).

    Raises
    ------
    ProtocolError
        Missing terminator, wrong tag, malformed header, short payload.
    ChecksumError
        Corrupted header values or payload.
    """
    end = data.find(b"\n", 0, LINE_MAX + 1)
    if end < 0:
        raise ProtocolError("frame reply: no complete header line")
    reply = parse_reply(data[: end + 1])
    check_tag(reply, tag)
    header = decode_frame_header(reply)
    if header is None:
        return None, end + 1
    payload = data[end + 1 : end + 1 + header.nbytes]
    return decode_frame(header, payload), end + 1 + header.nbytes


def check_tag(reply: Reply, tag: int | None) -> None:
    """Raise :class:`OutOfSequenceError` unless ``reply`` carries ``tag``."""
    if reply.tag != tag:
        raise OutOfSequenceError(f"reply tagged {reply.tag}, expected {tag}")


def check_header(reply: Reply, header: str, *, command: str = "") -> None:
    """Turn an ``ERR`` reply into :class:`InstrumentError`; reject a foreign header."""
    if reply.header == "ERR":
        code, message = parse_error_body(reply.body)
        raise InstrumentError(code, message, command=command)
    if reply.header != header:
        raise OutOfSequenceError(
            f"reply header {reply.header[:40]!r} does not answer {command or header!r}"
        )


def args_count_ok(spec: CommandSpec, cmd: Command) -> tuple[int, str] | None:
    """The SCPI error for a wrong argument count of ``cmd``, or ``None`` when it fits."""
    expected: int | None = spec.query_args if cmd.query else spec.set_args
    if expected is None:
        form = "query" if cmd.query else "set"
        return -113, f"{cmd.header} has no {form} form"
    if len(cmd.args) < expected:
        return -109, f"{cmd.text}: expects {expected} argument(s)"
    if len(cmd.args) > expected:
        return -108, f"{cmd.text}: expects {expected} argument(s)"
    return None


def parse_args_floats(cmd: Command) -> tuple[float, ...]:
    """Arguments of ``cmd`` as finite floats, or :class:`CommandError` (-104)."""
    out = []
    for a in cmd.args:
        if not _NUMBER_RE.fullmatch(a):
            raise CommandError(-104, f"{cmd.header}: argument {a!r} is not a number")
        v = float(a)
        if not math.isfinite(v):
            raise CommandError(-222, f"{cmd.header}: argument {a!r} is out of range")
        out.append(v)
    return tuple(out)
